"""Stage name -> factory and settings model, per kind of stage.

The YAML config names the implementation of each stage (``name:``) and the
registry validates its parameters with the stage's pydantic settings model.

The built-in stages are the rows of :data:`BUILTINS`: each names its settings
model and its factory as ``"module:attribute"``, imported on first use
(:attr:`StageSpec.settings`, :attr:`StageSpec.factory`). A run thus imports the
implementations it uses and no other: the config validates every filter's
settings, so the filters' models live apart from the filters
(``filters/settings.py``); the other kinds validate only the chosen stage's.

Third-party packages add stages through the entry-point group
``condtrack.stages``: each entry point names a module (imported, so that its
:func:`register` calls run) or a callable (called with no argument). Such a
plugin's stage is built with :meth:`StageSpec.build`, which calls it through
:meth:`StageSpec.call`: an exception of its own is a one-line CondtrackError
naming the stage, chained to it; a built-in's bug keeps its traceback.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from importlib import import_module, metadata
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:  # the settings models' base; pydantic itself loads with the first stage
    from pydantic import BaseModel

from condtrack_cli.errors import CondtrackError, plain, warn

#: The kinds of stage, in data-flow order.
KINDS = ("frames", "detect", "motion", "measure", "filter", "output")

ENTRY_POINT_GROUP = "condtrack.stages"

#: The built-in stages: kind, name, settings model, factory (each ``"module:attribute"``), summary.
BUILTINS = (
    ("frames", "auto", "condtrack_cli.frames.readers:FrameSettings", "condtrack_cli.frames.readers:open_frames",
     "a folder of images, a multi-page TIFF or a video file, chosen by the path"),
    ("detect", "shi_tomasi", "condtrack_cli.detect.shi_tomasi:ShiTomasiSettings",
     "condtrack_cli.detect.shi_tomasi:detect_points", "Shi-Tomasi corners that pass the trackability test"),
    ("motion", "dis", "condtrack_cli.motion.dense:DisMotionSettings", "condtrack_cli.motion.dense:make_dis_motion",
     "one dense DIS field per frame pair: local motion, its spread, the global fit"),
    ("motion", "robust", "condtrack_cli.motion.robust:RobustMotionSettings",
     "condtrack_cli.motion.local:make_robust_motion", "robust parametric motion, coarse to fine with IRLS"),
    ("motion", "regression", "condtrack_cli.motion.regression:RegressionSettings",
     "condtrack_cli.motion.regression:make_regression_motion",
     "the paper's: robust global fit, and a robust regression on the window around each position asked (slow)"),
    ("measure", "ssd", "condtrack_cli.measure.response:SSDSettings", "condtrack_cli.measure.ssd:make_ssd",
     "SSD matching with R_k from the correlation surface"),
    ("filter", "stk", "condtrack_cli.filters.settings:STKSettings", "condtrack_cli.filters.stk:make_stk",
     "Shi-Tomasi-Kanade baseline (OpenCV pyramidal Lucas-Kanade, forward-backward check)"),
    ("filter", "mdr", "condtrack_cli.filters.settings:MDRSettings", "condtrack_cli.filters.clf:make_mdr",
     "MDR baseline: the robust motion alone (global or local), no measurement"),
    ("filter", "clf", "condtrack_cli.filters.settings:CLFSettings", "condtrack_cli.filters.clf:make_clf",
     "conditional linear filter (paper §3, Fig. 1): global motion + SSD measurement"),
    ("filter", "cnlf", "condtrack_cli.filters.settings:CNLFSettings", "condtrack_cli.filters.cnlf:make_cnlf",
     "conditional nonlinear filter (paper §4, Fig. 2): particles, local motion, optimal proposal"),
    ("filter", "auto", "condtrack_cli.filters.settings:AutoSettings", "condtrack_cli.filters.auto:make_auto",
     "each point to the CLF or the CNLF by which motion its measurements follow (paper §5.3, revised)"),
    ("output", "csv", "condtrack_cli.io.interface:OutputSettings", "condtrack_cli.io.write:write_csv",
     "long CSV, one row per point per frame"),
    ("output", "hdf5", "condtrack_cli.io.interface:OutputSettings", "condtrack_cli.io.write:write_hdf5",
     "self-describing HDF5 with measurements and metadata"),
)


def _resolve(target):
    """``target`` itself, or the attribute a ``"module:attribute"`` string names (its module imported)."""
    if not isinstance(target, str):
        return target
    module, _, attribute = target.partition(":")
    return getattr(import_module(module), attribute)


@dataclass(frozen=True)
class StageSpec:
    """A registered stage: ``factory(settings, **context)`` builds it.

    ``settings_target`` and ``factory_target`` are the objects, or (a built-in's)
    ``"module:attribute"`` strings that :attr:`settings` and :attr:`factory` import.
    """

    kind: str
    name: str
    settings_target: type[BaseModel] | str
    factory_target: Callable | str
    summary: str

    @property
    def builtin(self) -> bool:
        """A row of :data:`BUILTINS` (named by strings), not a plugin's registered objects."""
        return isinstance(self.factory_target, str)

    @property
    def factory(self) -> Callable:
        return _resolve(self.factory_target)

    @property
    def settings(self) -> type[BaseModel]:
        return _resolve(self.settings_target)

    def build(self, *args, **kwargs):
        """The stage, ``factory(*args, **kwargs)``; a plugin's called through :meth:`call`, and so are the methods of
        what it builds (:class:`PluginStage`: a frame source, a motion stage's estimators, a measurer, a tracker),
        a plugin's measurer's outputs checked as well (``measure.interface.CheckedMeasurer``). A detect or output
        stage's factory is the stage's whole work: its value is returned as it is."""
        built = self.call(self.factory, *args, **kwargs)
        if self.builtin or self.kind in ("detect", "output"):
            return built
        if self.kind == "motion":  # a MotionStages (motion/interface.py): its state noise is condtrack's StateNoise
            source = built.field_source
            return dataclasses.replace(built, global_motion=PluginStage(built.global_motion, self),
                                       local_motion=PluginStage(built.local_motion, self),
                                       field_source=None if source is None else PluginStage(source, self))
        if self.kind == "measure":
            from condtrack_cli.measure.interface import CheckedMeasurer  # numpy: not loaded by ``condtrack --help``

            return CheckedMeasurer(PluginStage(built, self), self.name)
        return PluginStage(built, self)

    def call(self, function: Callable, *args, **kwargs):
        """``function(*args, **kwargs)``, a call into this stage. For a plugin's, an exception it raises (not a
        CondtrackError, nor a MemoryError) is a CondtrackError naming the stage and the plugin, chained to it
        (``__cause__``): one ``Error:`` line on the command line. A built-in's bug keeps its traceback."""
        if self.builtin:
            return function(*args, **kwargs)
        try:
            return function(*args, **kwargs)
        except (CondtrackError, MemoryError):
            raise
        except Exception as error:
            message = " ".join(str(error).split())  # one line
            raise CondtrackError(f"{self.label} raised {type(error).__name__}{': ' + message if message else ''}") \
                from error

    @property
    def label(self) -> str:
        """How messages name this stage: ``filter stage 'hold' (plugin thirdparty_hold)``, the plugin being the module
        of its factory (a built-in's: ``filter stage 'clf'``)."""
        if self.builtin:
            return f"{self.kind} stage '{self.name}'"
        return f"{self.kind} stage '{self.name}' (plugin {getattr(self.factory_target, '__module__', None) or '?'})"


#: The method of a stage that returns another stage (measure/interface.py: ``resized``), guarded as well.
_STAGE_RETURNING = ("resized",)
_END = object()
_MISSING = object()


class PluginStage:
    """A plugin's stage object, each of its attributes read (a property may raise) and its methods called through
    :meth:`StageSpec.call` (iterating it too): what they raise names the stage. ``hasattr`` answers as for the
    stage."""

    def __init__(self, stage, spec: StageSpec):
        self._stage, self._spec = stage, spec

    def __getattr__(self, attribute: str):
        found = self._spec.call(getattr, self._stage, attribute, _MISSING)
        if found is _MISSING:
            raise AttributeError(f"{type(self._stage).__name__!r} object has no attribute {attribute!r}")
        if not callable(found):
            return found
        if attribute in _STAGE_RETURNING:
            return lambda *args, **kwargs: PluginStage(self._spec.call(found, *args, **kwargs), self._spec)
        return functools.partial(self._spec.call, found)

    def __iter__(self):
        items = self._spec.call(iter, self._stage)
        try:
            while (item := self._spec.call(next, items, _END)) is not _END:
                yield item
        except GeneratorExit:  # left early: a generator (a video reader's) released now, not at collection
            if items is not self._stage and hasattr(items, "close"):
                self._spec.call(items.close)
            raise


_STAGES: dict[str, dict[str, StageSpec]] = {
    kind: {row[1]: StageSpec(*row) for row in BUILTINS if row[0] == kind} for kind in KINDS
}
_loaded = False


def register(kind: str, name: str, settings: type[BaseModel], summary: str = ""):
    """Decorator registering ``factory`` as stage ``name`` of ``kind``.

    ValueError for a ``settings`` model that is not a :class:`condtrack_cli.settings.StageSettings` (a plain pydantic
    model would take a misspelt key silently), or that has a field without a default: the config fills every stage's settings from
    the defaults (every filter's, whichever method runs), and the default config lists each key with its default.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown stage kind {kind!r}; valid kinds: {', '.join(KINDS)}")
    from condtrack_cli.settings import StageSettings  # pydantic: loaded by the plugin registering already

    if not (isinstance(settings, type) and issubclass(settings, StageSettings)):
        raise ValueError(f"{kind} stage {name!r}: settings {settings!r} is not a subclass of "
                         "condtrack_cli.settings.StageSettings (which refuses unknown keys and loose types)")
    required = [key for key, field in settings.model_fields.items() if field.is_required()]
    if required:
        raise ValueError(f"{kind} stage {name!r}: setting {', '.join(required)} has no default (every setting needs one)")

    def decorate(factory: Callable) -> Callable:
        first_doc_line = ((factory.__doc__ or "").strip().splitlines() or [""])[0]
        _STAGES[kind][name] = StageSpec(kind, name, settings, factory, summary or first_doc_line)
        return factory

    return decorate


def load_stages() -> None:
    """Load the entry points of ``condtrack.stages`` (once); the built-ins are registered already.

    An entry point that fails (a plugin's module missing or raising) is warned and skipped: the other stages work,
    and a config naming one of its stages is refused as naming an unknown stage.
    """
    global _loaded
    if _loaded:
        return
    _loaded = True
    for entry in metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            loaded = entry.load()
            if callable(loaded):
                loaded()
        except Exception as error:
            warn(f"{ENTRY_POINT_GROUP} entry point '{entry.name} = {entry.value}' not loaded, its stages left out "
                 f"({type(error).__name__}: {error})")


def reload_entry_points() -> None:
    """Forget what was loaded so that the next lookup scans entry points again."""
    global _loaded
    _loaded = False


def names(kind: str) -> list[str]:
    """Sorted names of the registered stages of ``kind``."""
    load_stages()
    return sorted(_STAGES[kind])


def get(kind: str, name: str) -> StageSpec:
    """The stage ``name`` of ``kind``; ValueError listing the valid names otherwise."""
    load_stages()
    try:
        return _STAGES[kind][name]
    except KeyError:
        valid = ", ".join(names(kind)) or "(none)"
        raise ValueError(f"unknown {kind} stage {plain(name)}; valid: {valid}") from None


#: Methods with fixed codes in track files (docs/schema.md): code i is ``BUILTIN_METHOD_CODES[i]``.
BUILTIN_METHOD_CODES = ("stk", "mdr", "clf", "cnlf")
#: Built-in filters that hand each point to other filters: their rows carry those filters' codes, none of their own.
ROUTERS = ("auto",)


def method_codes() -> tuple[str, ...]:
    """Names of the methods a track file can hold, in code order (``Tracks.method`` indexes this).

    The built-in codes come first and never move; every other registered filter
    (from an entry point) follows in name order.
    """
    extra = [name for name in names("filter") if name not in BUILTIN_METHOD_CODES + ROUTERS]
    return BUILTIN_METHOD_CODES + tuple(extra)


def method_code(name: str) -> int:
    """The code of method ``name`` in track files; ValueError naming the valid methods otherwise."""
    codes = method_codes()
    if name not in codes:
        raise ValueError(f"unknown method {plain(name)}; valid: {', '.join(codes)}")
    return codes.index(name)


def tracking_methods() -> tuple[str, ...]:
    """Every ``-m`` method in presentation order: the built-in ones, the routers, then the registered others."""
    codes = method_codes()
    return codes[: len(BUILTIN_METHOD_CODES)] + ROUTERS + codes[len(BUILTIN_METHOD_CODES):]

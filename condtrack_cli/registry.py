"""Stage name -> factory and settings model, per kind of stage.

A stage registers itself with :func:`register`; the YAML config names the
implementation of each stage (``name:``) and the registry validates its
parameters with the stage's pydantic settings model. Third-party packages add
stages through the entry-point group ``condtrack.stages``: each entry point
names a module (imported, so that its ``register`` calls run) or a callable
(called with no argument).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module, metadata
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:  # the settings models' base; pydantic itself loads with the first stage
    from pydantic import BaseModel

from condtrack_cli.errors import plain

#: The kinds of stage, in data-flow order.
KINDS = ("frames", "detect", "motion", "measure", "filter", "output")

ENTRY_POINT_GROUP = "condtrack.stages"

#: Modules of this package that register the built-in stages.
_BUILTIN_MODULES = (
    "condtrack_cli.frames.readers",
    "condtrack_cli.detect.shi_tomasi",
    "condtrack_cli.motion",
    "condtrack_cli.measure",
    "condtrack_cli.filters",
    "condtrack_cli.io.write",
)


@dataclass(frozen=True)
class StageSpec:
    """A registered stage: ``factory(settings, **context)`` builds it."""

    kind: str
    name: str
    factory: Callable
    settings: type[BaseModel]
    summary: str


_STAGES: dict[str, dict[str, StageSpec]] = {kind: {} for kind in KINDS}
_loaded = False


def register(kind: str, name: str, settings: type[BaseModel], summary: str = ""):
    """Decorator registering ``factory`` as stage ``name`` of ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"unknown stage kind {kind!r}; valid kinds: {', '.join(KINDS)}")

    def decorate(factory: Callable) -> Callable:
        first_doc_line = ((factory.__doc__ or "").strip().splitlines() or [""])[0]
        _STAGES[kind][name] = StageSpec(kind, name, factory, settings, summary or first_doc_line)
        return factory

    return decorate


def load_stages() -> None:
    """Import the built-in stages and the entry points of ``condtrack.stages`` (once)."""
    global _loaded
    if _loaded:
        return
    _loaded = True
    for module in _BUILTIN_MODULES:
        import_module(module)
    for entry in metadata.entry_points(group=ENTRY_POINT_GROUP):
        loaded = entry.load()
        if callable(loaded):
            loaded()


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

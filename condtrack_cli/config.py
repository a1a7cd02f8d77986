"""YAML configuration -> validated, frozen per-stage settings.

A config has one section per stage kind. ``frames``, ``detect``, ``motion`` and
``measure`` name their implementation with ``name:`` and give its parameters
beside it; ``filter`` names the tracking method with ``method:`` and holds one
sub-section of parameters per filter; ``output`` holds the writers' settings.
Every value is checked against the stage's settings model before any work
starts: an unknown key, a wrong type or an out-of-range value is refused with a
message naming the key and what is allowed.

``configs/default.yaml`` is :func:`default_yaml` written out; a test keeps the
two equal.
"""

from __future__ import annotations

import copy
import os
import re
from collections.abc import Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml
from pydantic import BaseModel, Field, ValidationError

from condtrack_cli import registry
from condtrack_cli.errors import CondtrackError, plain, python_value, read_error, warn
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.settings import StageSettings


#: Stage kinds whose section is ``name:`` plus that implementation's parameters.
NAMED_SECTIONS = ("frames", "detect", "motion", "measure")

#: Implementation used when a section gives no ``name``.
DEFAULT_NAMES = {"frames": "auto", "detect": "shi_tomasi", "motion": "dis", "measure": "ssd"}

#: Method used when neither the config nor ``-m`` names one.
DEFAULT_METHOD = "auto"

SECTION_DOCS = {
    "frames": "how frames are read (folder of images, multi-page TIFF or video)",
    "detect": "where points come from when no queries file is given, and the trackability test of queries",
    "motion": "motion between consecutive frames: local field, its noise and the global fit (paper §5.1)",
    "measure": "SSD matching of the reference patch and R_k from the correlation surface (§5.2)",
    "filter": "the tracking method and each filter's parameters",
    "output": "the CSV and HDF5 writers",
}


@dataclass(frozen=True)
class StageConfig:
    """The implementation chosen for one stage and its validated settings."""

    name: str
    settings: StageSettings


@dataclass(frozen=True)
class Config:
    """A whole validated configuration."""

    stages: Mapping[str, StageConfig]  #: one per NAMED_SECTIONS
    method: str
    filters: Mapping[str, StageSettings]  #: settings of every registered filter
    output: OutputSettings
    smooth: bool = False  #: ``filter.smooth``: two-way smoothing of each pass (``filters/smoother.py``)

    def stage(self, kind: str) -> StageConfig:
        return self.stages[kind]

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration as plain data (what the HDF5 file stores)."""
        out: dict[str, Any] = {}
        for kind in NAMED_SECTIONS:
            stage = self.stages[kind]
            out[kind] = {"name": stage.name, **stage.settings.model_dump()}
        out["filter"] = {"method": self.method, "smooth": self.smooth, **{n: s.model_dump() for n, s in self.filters.items()}}
        out["output"] = self.output.model_dump()
        return out

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def check_fits_frame(self, width: int, height: int, detecting: bool = True, where: str = "input") -> None:
        """Refuse a frame smaller than every setting allows, or a window (``frame_windows`` of the stages and of the
        filters the method uses: its settings' ``stage_kinds``) larger than a ``width`` x ``height`` frame; ``where``
        names the input.

        ``detecting``: points are detected (no queries file), so the detector's
        windows count too; with queries they are only read on the query points,
        where a window larger than the frame is clipped.
        """
        read = {"frames", *(["detect"] if detecting else []), *registry.get("filter", self.method).settings.stage_kinds}
        sections = {kind: stage.settings for kind, stage in self.stages.items() if kind in read}
        sections.update({f"filter.{name}": self.filters[name] for name in filters_used_by(self.method)})
        windows = [(f"{prefix}.{field}", getattr(settings, field), _minimum(type(settings), field))
                   for prefix, settings in sections.items() for field in settings.frame_windows]
        smallest = max((minimum for _, _, minimum in windows), default=1)
        if min(width, height) < smallest:  # no setting makes it fit: the frame is the problem, not a key
            raise CondtrackError(f"{where}: the {width}x{height} frame is too small for tracking "
                                 f"(at least {smallest}x{smallest} px)")
        for kind in read & self.stages.keys():  # a stage that cannot run on so small a frame whatever its windows
            least = self.stages[kind].settings.least_longer_side()
            if max(width, height) < least:
                raise CondtrackError(f"{where}: the {width}x{height} frame is too small for {kind} "
                                     f"'{self.stages[kind].name}' (at least {least} px on one side)")
        oversized = [(key, side) for key, side, _ in windows if side > min(width, height)]
        if oversized:  # every one named at once: fixing them one run at a time is what a user should not have to do
            (key, side), others = oversized[0], oversized[1:]
            nor = f"; nor do {', '.join(f'{other} ({size} px)' for other, size in others)}" if others else ""
            raise CondtrackError(f"config key '{key}': a window of {side} px does not fit in the "
                                 f"{width}x{height} frame (at most {min(width, height)}){nor}")


def _minimum(model: type[BaseModel], field: str) -> int:
    """The smallest value the settings model allows for ``field`` (its ``ge`` bound, 1 without one)."""
    bounds = [getattr(item, "ge", None) for item in model.model_fields[field].metadata]
    return max([bound for bound in bounds if bound is not None], default=1)


def valid_methods() -> list[str]:
    """Tracking methods: the registered filters (the router ``auto`` is one of them)."""
    return registry.names("filter")


def check_method(method: str) -> None:
    """CondtrackError naming the key ``filter.method`` and the valid methods when ``method`` is not registered."""
    if method not in valid_methods():
        raise CondtrackError(f"config key 'filter.method': unknown method {plain(method)}; valid: {', '.join(valid_methods())}")


def _format_validation_error(prefix: str, error: ValidationError, model: type[BaseModel]) -> str:
    first = error.errors()[0]
    key = ".".join([prefix, *map(str, first["loc"])])
    if first["type"] == "extra_forbidden":
        valid = ", ".join(model.model_fields)
        return f"config key '{key}': unknown key; valid keys: {valid}"
    if first["type"] == "value_error" and not first["loc"]:  # a rule across keys: the message names them
        return f"config key '{key}': {first['ctx']['error']}"
    got = first.get("input")
    return f"config key '{key}': {first['msg']} (got {plain(got)})"


def _validate(prefix: str, model: type[StageSettings], params: Any) -> StageSettings:
    if not isinstance(params, dict):
        raise CondtrackError(f"config key '{prefix}': expected a mapping of keys to values, got {plain(params)}")
    try:
        return model.model_validate(params)
    except ValidationError as error:
        raise CondtrackError(_format_validation_error(prefix, error, model)) from None


def _section(raw: Any) -> Any:
    """A section as given, an empty mapping for an empty one (``filter:`` alone, YAML null); any other value, even a
    false one (``[]``, ``0``, ``false``, ``""``), is kept for the caller to refuse as not a mapping."""
    return {} if raw is None else raw


def _named_section(kind: str, raw: Any) -> StageConfig:
    raw = _section(raw)
    if not isinstance(raw, dict):
        raise CondtrackError(f"config key '{kind}': expected a mapping, got {plain(raw)}")
    raw = dict(raw)
    name = raw.pop("name", DEFAULT_NAMES[kind])
    try:
        spec = registry.get(kind, name)
    except ValueError as error:
        raise CondtrackError(f"config key '{kind}.name': {error}") from None
    return StageConfig(name, _validate(kind, spec.settings, raw))


def resolve(raw: Mapping[str, Any]) -> Config:
    """Validate a raw config mapping (YAML already parsed); raise CondtrackError."""
    allowed = (*NAMED_SECTIONS, "filter", "output")
    for key in raw:
        if key not in allowed:
            raise CondtrackError(f"config key '{key}': unknown section; valid sections: {', '.join(allowed)}")
    stages = {kind: _named_section(kind, raw.get(kind)) for kind in NAMED_SECTIONS}
    filter_raw = _section(raw.get("filter"))
    if not isinstance(filter_raw, dict):
        raise CondtrackError(f"config key 'filter': expected a mapping, got {plain(filter_raw)}")
    filter_raw = dict(filter_raw)
    method = filter_raw.pop("method", DEFAULT_METHOD)
    check_method(method)
    smooth = filter_raw.pop("smooth", False)
    if not isinstance(smooth, bool):
        raise CondtrackError(f"config key 'filter.smooth': expected true or false, got {plain(smooth)}")
    filters = {}
    for name in registry.names("filter"):
        settings = registry.get("filter", name).settings
        filters[name] = _validate(f"filter.{name}", settings, _section(filter_raw.pop(name, None)))
    if filter_raw:
        key = next(iter(filter_raw))
        raise CondtrackError(
            f"config key 'filter.{key}': unknown key; valid keys: method, smooth, {', '.join(registry.names('filter'))}"
        )
    if smooth and not registry.get("filter", method).settings.smoother:
        raise CondtrackError(f"config key 'filter.smooth': method {method!r} has no smoother")
    output = _validate("output", OutputSettings, _section(raw.get("output")))
    return Config(stages=stages, method=method, filters=filters, output=output, smooth=smooth)


class DuplicateKey(yaml.constructor.ConstructorError):
    """A mapping that gives one key twice (PyYAML would keep the last silently)."""

    def __init__(self, key: Any, line: int):
        super().__init__(problem=f"key {key!r} given twice")
        self.key, self.line = key, line


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping with :class:`DuplicateKey`, and reading
    every float with an exponent as a float (``_EXPONENT_FLOAT``)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # '<<' merges another mapping, whose keys the explicit ones may override
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, Hashable):
                if key in seen:
                    raise DuplicateKey(key, key_node.start_mark.line + 1)
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


#: A float with an exponent that YAML 1.1 (PyYAML) reads as a string: ``1e-3``, ``1E16``, ``2.5e3`` (no dot, or an
#: unsigned exponent). Python, C and YAML 1.2 read these as floats, and so does the config.
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$")
_UniqueKeyLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789."))


def parse_yaml(text: str) -> Any:
    """``text`` parsed as YAML (safe types only); a key given twice raises :class:`DuplicateKey`."""
    return yaml.load(text, Loader=_UniqueKeyLoader)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``'measure.template=15'`` -> (['measure', 'template'], 15); the value is read as YAML."""
    key, sep, value = text.partition("=")
    path = key.strip().split(".")
    if not sep or not all(path):
        raise CondtrackError(f"--set {text!r}: expected section.key=value")
    try:
        parsed = parse_yaml(value)
    except DuplicateKey as error:
        raise CondtrackError(f"--set {text!r}: key {error.key!r} given twice") from None
    except yaml.YAMLError:
        raise CondtrackError(f"--set {text!r}: the value is not valid YAML") from None
    return path, parsed


def _apply_override(raw: dict, path: list[str], value: Any, name: str, set_by: dict[tuple[str, ...], str]) -> None:
    """Set the key ``path`` of ``raw`` to ``value``, for the option ``name`` (``--set a.b=1``, ``--smooth``, ``-m``).

    ``set_by``: the option that set each key path before (updated); a section that one of them set to a value
    (``--set filter=3``) is blamed on it, not on ``name``.
    """
    node = raw
    for depth, part in enumerate(path[:-1]):
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            key = tuple(path[: depth + 1])
            raise CondtrackError(f"{set_by.get(key, name)}: config key '{'.'.join(key)}' is {plain(child)}, "
                                 "not a section")
        node = child
    node[path[-1]] = value
    set_by[tuple(path)] = name


def read_yaml(path: str | Path) -> dict:
    """Parse a config file into a mapping; CondtrackError naming the file otherwise."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise read_error(error, f"cannot read config file {str(path)!r}: {error.strerror or error}") from None
    except UnicodeDecodeError as error:
        raise CondtrackError(f"config file {str(path)!r} is not UTF-8 text (byte {error.object[error.start]:#04x} "
                             f"at offset {error.start})") from None
    try:
        raw = parse_yaml(text)
    except DuplicateKey as error:
        raise CondtrackError(f"config file {str(path)!r}, line {error.line}: key {error.key!r} given twice") from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        said = [part for part in (getattr(error, "context", None), getattr(error, "problem", None)) if part]
        why = f": {', '.join(said)}" if said else ""  # PyYAML's words: a second '---' "expected a single document ..."
        raise CondtrackError(f"config file {str(path)!r} is not valid YAML{where}{why}") from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise CondtrackError(f"config file {str(path)!r}: expected a mapping of sections at the top level")
    return raw


def filters_used_by(method: str) -> tuple[str, ...]:
    """The ``filter.<name>`` sections that ``method`` reads: its own and its settings' ``filter_sections``."""
    return (method, *registry.get("filter", method).settings.filter_sections)


def _unused_because(config: Config, path: list[str]) -> str | None:
    """Why setting the config key ``path`` changes nothing under ``config``'s method, or None when it may."""
    method = config.method
    settings = registry.get("filter", method).settings
    if path == ["output", "max_std"] and not settings.covariance:
        return f"method '{method}' writes no covariance"
    if path[0] in ("motion", "measure") and path[0] not in settings.stage_kinds:
        return f"method '{method}' runs no {path[0]} stage"
    if len(path) < 3 or path[0] != "filter" or path[1] not in valid_methods() or path[1] in filters_used_by(method):
        return None
    users = [name for name in valid_methods() if path[1] in filters_used_by(name)]
    return f"method '{method}' does not use filter.{path[1]} (-m {' or -m '.join(users)} would)"


def stored_config(path: str | Path, meta: Mapping[str, Any]) -> Config | None:
    """The resolved config in the root attributes ``meta`` of the track file ``path`` (None: it holds none, a CSV);
    CondtrackError naming the file when it is no YAML mapping; None, with a warning naming the file, when this version
    does not take it (another version's, with a key since renamed or removed: its tracks are read all the same)."""
    if "config" not in meta:
        return None
    try:
        raw = yaml.safe_load(meta["config"])
    except yaml.YAMLError:
        raise CondtrackError(f"{path}: damaged or incomplete condtrack HDF5 file (root attribute 'config' is not "
                             "valid YAML)") from None
    if not isinstance(raw, dict):
        raise CondtrackError(f"{path}: damaged or incomplete condtrack HDF5 file (root attribute 'config' is not a "
                             "mapping of sections)")
    try:
        return resolve(raw)
    except CondtrackError as error:
        warn(f"{path}: root attribute 'config' is not a config of this version ({error}): read without it (config None)")
        return None


def load_config(
    path: str | os.PathLike | Mapping[str, Any] | None = None, overrides: list[str] = (), method: str | None = None,
    options: Mapping[str, str] | None = None, csv_output: bool = False,
) -> Config:
    """The validated config: defaults, then the file (or a nested mapping), then ``--set`` overrides, then the
    overrides of ``options``, then ``-m``.

    ``options``: overrides that options or arguments make, by the option's name
    (``{"--max-std": "output.max_std=3.0"}``). An override that the chosen method
    does not read (a filter section it does not use, ``output.max_std`` without
    a covariance) gets a warning naming the ``--set`` or the option. ``csv_output``: the run writes CSV, which holds
    none of the datasets ``output.store_<name>`` switches on (warned here, once for a whole batch).
    """
    if path is not None and not isinstance(path, (str, os.PathLike, Mapping)):
        raise CondtrackError(f"config: expected a YAML path or a nested mapping, got {type(path).__name__}")
    raw = read_yaml(path) if isinstance(path, (str, os.PathLike)) else python_value(dict(path or {}))  # np.int64(50) is 50
    raw = copy.deepcopy(raw)
    given = [(f"--set {text}", text) for text in overrides] + list((options or {}).items())
    parsed = [(name, parse_override(text)) for name, text in given]
    set_by = {}
    for name, override in parsed:
        _apply_override(raw, *override, name, set_by)
    _warn_overridden(parsed[: len(overrides)], parsed[len(overrides) :]
                     + ([("-m", (["filter", "method"], method))] if method is not None else []))
    if method is not None:
        written = raw.get("filter")
        if isinstance(written, dict) and "method" in written:  # a bad value stays bad under -m
            check_method(written["method"])
        _apply_override(raw, ["filter", "method"], method, f"-m {method}", set_by)
    config = resolve(raw)
    for name, (key_path, _) in parsed:
        reason = _unused_because(config, key_path)
        if reason:
            warn(f"{name} has no effect: {reason}")
    for message in _unwritten_extras(config, csv_output):
        warn(message)
    return config


def _unwritten_extras(config: Config, csv_output: bool) -> list[str]:
    """A warning for each ``output.store_<name>`` switched on (by any source) whose dataset ``config``'s method does not
    write (its settings' ``extras``): ``store_particles`` under ``clf``, ``store_segmentation`` under ``cnlf``; then
    (``csv_output``) one for each it writes, which a CSV has no room for."""
    method = config.method
    switched_on = [name for name in ("particles", "segmentation") if getattr(config.output, f"store_{name}")]
    written = [name for name in switched_on if name in registry.get("filter", method).settings.extras]
    messages = []
    for name in switched_on:
        if name not in written:
            writers = [other for other in valid_methods() if name in registry.get("filter", other).settings.extras]
            messages.append(f"output.store_{name} has no effect: method '{method}' writes no {name} "
                            f"(-m {' or -m '.join(writers)} would)")
    return messages + [not_in_csv(name) for name in written if csv_output]


def not_in_csv(name: str) -> str:
    """The warning for the optional dataset ``name`` (``output.store_<name>``) of a run that writes a CSV."""
    return f"output.store_{name} has no effect: a CSV holds no {name} (write an .h5 file for them)"


def _warn_overridden(sets: list[tuple[str, tuple[list[str], Any]]],
                     later: list[tuple[str, tuple[list[str], Any]]]) -> None:
    """Warn for each ``--set`` (name, (key path, value)) in ``sets`` that an option of ``later`` (``--forward-only``,
    ``-m``, ...) sets to another value: the option is applied after it, so it has no effect."""
    for name, (path, value) in sets:
        for option, (option_path, option_value) in later:
            if option_path == path and option_value != value:
                warn(f"{name} has no effect: {option} sets {'.'.join(path)} to {yaml_scalar(option_value)}")


def yaml_scalar(value: Any) -> str:
    """``value`` written as YAML reads it back (``.inf`` for inf, ``'3'`` for the string "3"): an override's text."""
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()


def _settings_lines(model: type[BaseModel], indent: str) -> list[str]:
    lines = []
    for key, field in model.model_fields.items():
        value = yaml_scalar(field.default)
        lines.append(f"{indent}{key}: {value}  # {field.description}")
    return lines


def default_yaml() -> str:
    """The default configuration as commented YAML (the text of configs/default.yaml)."""
    lines = [
        "# condtrack default configuration: every key, with its default and meaning.",
        "# Generated by `condtrack stages --default-config`; tests keep it equal to the code.",
        "",
    ]
    for kind in NAMED_SECTIONS:
        spec = registry.get(kind, DEFAULT_NAMES[kind])
        lines.append(f"{kind}:  # {SECTION_DOCS[kind]}")
        lines.append(f"  name: {spec.name}  # implementation; see `condtrack stages` for the others")
        lines += _settings_lines(spec.settings, "  ")
        lines.append("")
    lines.append(f"filter:  # {SECTION_DOCS['filter']}")
    lines.append(f"  method: {DEFAULT_METHOD}  # one of: {', '.join(valid_methods())} (-m overrides)")
    lines.append("  smooth: false  # two-way smoothing: each frame's estimate also uses the later frames (--smooth; clf, cnlf, auto)")
    for name in registry.names("filter"):
        spec = registry.get("filter", name)
        lines.append(f"  {name}:  # {spec.summary}")
        lines += _settings_lines(spec.settings, "    ")
    lines.append("")
    lines.append(f"output:  # {SECTION_DOCS['output']}")
    lines += _settings_lines(OutputSettings, "  ")
    return "\n".join(lines) + "\n"


def config_keys() -> list[str]:
    """Every key of the default configuration, dotted (``measure.template``), in its order: what ``--set`` completes."""

    def walk(mapping: dict, prefix: str) -> list[str]:
        return [key for name, value in mapping.items()
                for key in (walk(value, f"{prefix}{name}.") if isinstance(value, dict) else [f"{prefix}{name}"])]

    return walk(yaml.safe_load(default_yaml()), "")


__all__ = ["Config", "StageConfig", "StageSettings", "OutputSettings", "load_config", "resolve", "default_yaml", "config_keys", "Field", "Literal"]

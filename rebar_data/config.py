"""The machinery every config schema uses: ``Strict`` models (unknown keys are errors: a typo must never be
silently ignored), the bounded YAML reader, and one clear message for a bad value, naming the field, the value and
what is accepted.

The schemas themselves sit beside what they configure: the mesh in :mod:`rebar_data.geometry.config`, the scene
in :mod:`rebar_data.scene.config`, a whole pipeline file in :mod:`rebar_data.pipeline`, the servo suites in
:mod:`rebar_data.servo.config`, training in :mod:`rebar_data.perception.training.config`.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Annotated, Any, get_args

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rebar_data.errors import ConfigError  # noqa: F401  (raised by every config reader)

Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
Fraction = Annotated[float, Field(ge=0, le=1)]
PositiveInt = Annotated[int, Field(gt=0)]
NonNegativeInt = Annotated[int, Field(ge=0)]
Vec3 = tuple[float, float, float]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


_SEMVER = re.compile(r"^\d+\.\d+\.\d+$")

# the paper's pipeline in the project's `pipelines/` folder: what the benches build, render and servo on
PAPER_PIPELINE = Path(__file__).resolve().parents[1] / "pipelines" / "paper-tunnel.yaml"


MAX_YAML_NODES = 200_000
"""The most values (mappings, lists and scalars, each alias counted as what it stands for) a config may
expand to: far above any real config (a pipeline is a few hundred), far below what nested aliases (a
"billion laughs") make of a few lines."""

EXCERPT_CHARS = 80  # the most of a bad value a message shows


def excerpt(value: Any, limit: int = EXCERPT_CHARS) -> str:
    """``repr(value)``, cut to ``limit`` characters (with ``...``) so that a message stays one short line."""
    if isinstance(value, list | tuple | dict) and len(value) > 64:
        kind = type(value).__name__
        return f"a {kind} of {len(value)} items"
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _expanded_size(root: yaml.Node, limit: int) -> int | None:
    """How many nodes ``root`` stands for with every alias expanded (shared nodes counted at each use),
    counted up to ``limit + 1``; None when a node holds itself (an anchor used inside its own value). Each
    node is sized once, so a deep alias chain costs its length, not what it expands to."""
    sizes: dict[int, int] = {}
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if key in sizes and not children_done:
            continue
        if isinstance(node, yaml.ScalarNode):
            sizes[key] = 1
            continue
        items = node.value if isinstance(node, yaml.SequenceNode) else [x for kv in node.value for x in kv]
        if not children_done:
            sizes[key] = -1  # being sized
            stack.append((node, True))
            stack.extend((c, False) for c in items if id(c) not in sizes)
            continue
        if any(sizes[id(c)] == -1 for c in items):
            return None  # a child still being sized is an ancestor: the node holds itself
        sizes[key] = min(limit + 1, 1 + sum(sizes[id(c)] for c in items))
    return sizes[id(root)]


def parse_yaml(text: str, source: str) -> Any:
    """The YAML document in ``text`` (``source`` names it in messages): PyYAML's safe loader (plain data,
    no Python objects), refusing a document whose aliases expand past ``MAX_YAML_NODES`` values."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = _expanded_size(node, MAX_YAML_NODES)
        if size is None:
            raise ConfigError(
                f"{source}: an anchor (&name) is used inside its own value, which never ends; accepted: "
                "aliases (*name) of finished sections only"
            )
        if size > MAX_YAML_NODES:
            raise ConfigError(
                f"{source}: its aliases (*name) expand to more than {MAX_YAML_NODES:,} values; accepted: a "
                "config that repeats a section a few times, not repeats nested in repeats"
            )
        return loader.construct_document(node)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise ConfigError(f"{source}: not valid YAML{where}: {getattr(e, 'problem', None) or e}") from None
    finally:
        loader.dispose()


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping, turning every way a file can be unusable into a ConfigError. The file is read
    once (a pipe such as ``<(...)`` can be read only once) and parsed from those bytes."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{p}: no such config file; accepted: a YAML file such as pipelines/smoke.yaml")
    if p.is_dir():
        raise ConfigError(f"{p}: is a folder; accepted: a YAML config file")
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        text = "\0"
    except OSError as e:
        raise ConfigError(
            f"{p}: cannot be read ({e.strerror}); accepted: a YAML config file you may read"
        ) from None
    if "\0" in text:
        raise ConfigError(f"{p}: not a text file; accepted: a YAML config file such as pipelines/smoke.yaml")
    data = parse_yaml(text, str(p))
    if not isinstance(data, dict):
        empty = " (it is empty)" if not text.strip() else ""
        raise ConfigError(f"{p}: the top level is {type(data).__name__}{empty}; accepted: a mapping of keys")
    return data


def validate(model: type[BaseModel], data: dict[str, Any], source: str) -> Any:
    """Validate ``data`` against ``model``; the first problem becomes one ConfigError sentence."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation_error(e, source, data, model)) from None


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic models an annotation can hold (through Optional, unions, lists, dicts and Annotated)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in get_args(annotation) for m in _models_in(arg)]


def accepted_keys(model: type[BaseModel], loc: tuple) -> list[str] | None:
    """The keys the model accepts at ``loc`` (an error location without its last key), or None when the
    location does not lead to one model."""
    models = [model]
    for item in loc:
        if isinstance(item, int):
            continue  # a list index: the element's models are already those of the list
        named = [m for m in models if item in m.model_fields]
        if named:
            models = [x for m in named for x in _models_in(m.model_fields[item].annotation)]
            continue
        tagged = [  # a union's tag: the member whose kind is the tag, or its class name
            m
            for m in models
            if m.__name__ == item or item in get_args(getattr(m.model_fields.get("kind"), "annotation", None))
        ]
        if tagged:
            models = tagged
        # otherwise a dict key: the values' models stay
    return sorted(models[0].model_fields) if len(models) == 1 else None


def format_validation_error(
    e: ValidationError, source: str, data: Any = None, model: type[BaseModel] | None = None
) -> str:
    err = e.errors(include_url=False)[0]
    path = [x for x in err["loc"] if not _is_union_tag(x)]
    loc = ".".join(str(x) for x in path)
    kind, msg = err["type"], err["msg"]
    value = err.get("input")
    if kind == "extra_forbidden":
        keys = accepted_keys(model, tuple(err["loc"][:-1])) if model is not None else None
        if not keys:
            return (
                f"{source}: unknown key '{loc}'; check its spelling (accepted keys are listed in the README)"
            )
        close = difflib.get_close_matches(str(path[-1]), keys, n=1)
        where = ".".join(str(x) for x in path[:-1]) or "the top level"
        hint = f"did you mean '{close[0]}'? " if close else ""
        return f"{source}: unknown key '{loc}'; {hint}accepted at {where}: {', '.join(keys)}"
    if kind == "missing" and path and isinstance(path[-1], int):
        parent = ".".join(str(x) for x in path[:-1])
        given = _lookup(data, path[:-1])
        return f"{source}: {parent} = {excerpt(given)} is not accepted: it needs more than {path[-1]} items"
    if kind == "missing":
        return f"{source}: '{loc}' is required but missing"
    if kind == "value_error":
        msg = msg.removeprefix("Value error, ")
        return f"{source}: {loc + ': ' if loc else ''}{msg}"
    shown = excerpt(value) if not isinstance(value, dict) else "a mapping"
    return f"{source}: {loc} = {shown} is not accepted: {msg[0].lower() + msg[1:]}"


def _lookup(data: Any, path: list) -> Any:
    for key in path:
        try:
            data = data[key]
        except (KeyError, IndexError, TypeError):
            return None
    return data


# values of the ``kind`` discriminators; pydantic puts the chosen one into error locations
UNION_TAGS = {"planar", "tunnel_segment", "ifc", "orbit_arc", "straight_pass", "approach", "random_look_at"}


def _is_union_tag(x: object) -> bool:
    return isinstance(x, str) and x in UNION_TAGS


def semver(value: str) -> str:
    if not _SEMVER.match(value):
        raise ValueError(f"version = {excerpt(value)} is not accepted: use MAJOR.MINOR.PATCH, such as 1.0.0")
    return value

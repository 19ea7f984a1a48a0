"""Reference pages generated from the code, so they cannot drift from it.

* :func:`scenario_reference`: every key of the scenario file, walked from the pydantic schema
  (:class:`swarmpc.config.Scenario` and its nested models): dotted path, type, default, meaning.
  The meaning is the field's ``Field(description=...)`` or, failing that, an entry of
  :data:`MEANINGS`; a schema field with neither raises :class:`MissingDocError`.
* :func:`cli_reference`: every command and parameter of the ``swarmpc`` command line, read from
  the typer app.
* :func:`run_folder_reference`: every file, ``summary.json`` key and array of a run folder, from
  the tables of :mod:`swarmpc.simulation.contract`, and the export formats of :mod:`swarmpc.export`.

``python -m swarmpc.docgen`` prints the scenario reference (``> docs/scenario-reference.md``);
``python -m swarmpc.docgen --write`` writes every page into ``docs/``.
"""

from __future__ import annotations

import enum
import sys
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from swarmpc.config import Scenario, scenario_from_dict
from swarmpc.simulation.contract import ARRAYS, CONDITIONS, FILES, SUMMARY_KEYS

# Meanings of the schema fields that carry no ``Field(description=...)``, by dotted path
# (list items as ``[]``). Keep one line each; the table shows type and default separately.
MEANINGS: dict[str, str] = {
    "dim": "Spatial dimension: 2 (ground robots) or 3 (drones). Every position below has `dim` entries.",
    "dt": "Sampling time [s] of the dynamics and of the MPC; > 0.",
    "collision": (
        "OBCA form: `hard` (certificate ≥ d_min) or `soft` (certificate ≥ d_min − α, α ≥ 0 costs κα). "
        "See [concepts](concepts.md)."
    ),
    "d_min": (
        "Margin [m] the certificate keeps between an agent's position and another agent's box (or an "
        "obstacle). Must be > 0 with `collision: hard` (0 lets λ = 0 pass and excludes nothing); >= 0 with soft."
    ),
    "kappa": "Weight κ of the soft form's slack α in the cost; > 0. Unused with `collision: hard`.",
    "discretization": (
        "`euler` (the paper's first-order step; collision and workspace constraints on k = 2..N) or "
        "`zoh` (exact zero-order hold; constraints on k = 1..N)."
    ),
    "weights": (
        "Cost weights of every agent: Σ_k (s_k − s_g)ᵀQ(s_k − s_g) + u_kᵀRu_k, "
        "plus (s_N − s_g)ᵀQf(s_N − s_g)."
    ),
    "weights.Q": "State weight: a scalar ≥ 0 (times identity) or a symmetric PSD 2·dim × 2·dim matrix.",
    "weights.R": "Input weight: a scalar > 0 (times identity) or a symmetric PSD dim × dim matrix.",
    "workspace": (
        "Box bound on every agent's position, a constraint of every OCP. `null`: no position bound; "
        "RRT then samples the starts' and goals' bounding box padded by 1 m."
    ),
    "workspace.lower": "Lower corner, `dim` values, below `upper` on every axis. Starts and goals must lie inside.",
    "workspace.upper": "Upper corner, `dim` values.",
    "limits": "Optional actuator and speed limits, imposed in every OCP; `null` leaves a limit off.",
    "obstacles[].box": "An axis-aligned box obstacle.",
    "obstacles[].box.center": "Centre of the box, `dim` values.",
    "obstacles[].box.half_size": "Half-size of the box per axis, `dim` values, each > 0.",
    "obstacles[].polytope": "A convex polytope obstacle {p : G p ≤ g}.",
    "obstacles[].polytope.g": "Facet offsets, one per row of G.",
    "agents[].start": "Start: a position (`dim` values, at rest) or a full state [position, velocity] (2·dim values).",
    "agents[].goal": "Goal: a position (`dim` values, at rest) or a full state [position, velocity] (2·dim values).",
    "solver": "How each MPC step is solved.",
    "solver.method": (
        "`admm`: consensus ADMM, one OCP per agent; `centralized`: one OCP over all agents "
        "(the optimality reference, faster for small swarms)."
    ),
    "solver.initial_guess": (
        "Initial guess of every solve: `straight` line to the goal, `shifted` previous plan, `rrt` "
        "(OMPL RRT-Connect around the obstacles), `auto` (shifted while the last solve succeeded, else RRT "
        "with obstacles and straight without). With `rrt`/`auto` a blocked agent also tracks an RRT waypoint."
    ),
    "stop": "When the closed loop ends.",
}

# A small valid scenario shown at the top of the reference (validated when the page is built).
EXAMPLE = """\
name: crossing
dim: 2
delta: 0.3
collision: hard
workspace: {lower: [-3, -3], upper: [3, 3]}
obstacles:
  - {box: {center: [0, 1.5], half_size: [0.3, 0.3]}}
agents:
  - {start: [-2, 0], goal: [2, 0]}
  - {start: [2, 0.2], goal: [-2, 0.2]}
solver: {method: admm, rho: 1.0}
stop: {max_steps: 300}
"""

RULES = """\
Checks beyond the single fields (the first failing one is reported, naming the field):

- `delta`, `workspace.*`, `limits.accel`, `obstacles[].box.*`, the columns of `obstacles[].polytope.G`
  must have `dim` entries (or be scalars where a scalar is allowed);
  `agents[].start` / `goal` must have `dim` or 2·`dim` entries.
- `collision: hard` needs `d_min > 0`.
- `weights.*` matrices must be square of the right size, symmetric and positive semidefinite.
- No two starts (nor two goals) whose bodies overlap (closer than b_i + b_j on every axis, Δ with
  the default bodies); starts and goals inside the workspace and outside every obstacle grown by
  the agent's body.
- Numbers must be finite; unknown keys are an error.
"""


class MissingDocError(RuntimeError):
    """A schema field has neither a ``Field(description=...)`` nor an entry in :data:`MEANINGS`."""


@dataclass(frozen=True)
class FieldDoc:
    """One row of the scenario reference."""

    path: str
    type: str
    default: str
    meaning: str


def _nested_models(annotation: Any) -> list[tuple[type[BaseModel], bool]]:
    """Pydantic models inside an annotation, each with whether it sits in a list."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [(annotation, False)]
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is list:
        return [(model, True) for model, _ in _nested_models(args[0])]
    if origin in (typing.Union, types.UnionType):
        return [found for arg in args for found in _nested_models(arg)]
    return []


_SCALARS = {float: "number", int: "integer", str: "string", bool: "boolean", type(None): "null"}


def type_label(annotation: Any) -> str:
    """A YAML-oriented name of a type annotation (no ``|``, which would break a markdown table)."""
    if annotation in _SCALARS:
        return _SCALARS[annotation]
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "mapping"
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is Literal:
        return "one of " + ", ".join(f"`{a}`" for a in args)
    if origin is list:
        inner = type_label(args[0])
        if inner == "list of numbers":
            return "matrix (list of rows)"
        return f"list of {inner}s" if inner in ("number", "integer", "string", "mapping") else f"list of ({inner})"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(type_label(a) for a in args)
    raise MissingDocError(f"no label for the annotation {annotation!r}")


def _constraint_label(info: FieldInfo) -> str:
    parts = []
    for item in info.metadata:
        for attr, sign in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            value = getattr(item, attr, None)
            if value is not None:
                parts.append(f"{sign} {value}")
    return ", ".join(parts)


def default_label(info: FieldInfo) -> str:
    """The default as it would be written in YAML; ``required`` when there is none."""
    if info.is_required():
        return "required"
    value = info.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        return "(section)"
    if value is PydanticUndefined:
        return "required"
    return "`" + yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip() + "`"


def schema_fields(model: type[BaseModel] = Scenario, prefix: str = "") -> list[FieldDoc]:
    """Every key of ``model`` depth first, nested models right after their parent key.

    Raises :class:`MissingDocError` when a field has no description and no :data:`MEANINGS` entry.
    """
    rows: list[FieldDoc] = []
    for name, info in model.model_fields.items():
        path = f"{prefix}{name}"
        meaning = info.description or MEANINGS.get(path)
        if not meaning:
            raise MissingDocError(
                f"scenario field {path!r} has no description: add Field(description=...) in "
                f"swarmpc/config.py or an entry to MEANINGS in swarmpc/docgen.py"
            )
        label = type_label(info.annotation)
        constraint = _constraint_label(info)
        if constraint:
            label = f"{label}, {constraint}"
        rows.append(FieldDoc(path, label, default_label(info), meaning))
        for nested, in_list in _nested_models(info.annotation):
            rows.extend(schema_fields(nested, f"{path}[]." if in_list else f"{path}."))
    return rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def scenario_reference() -> str:
    """The scenario-file reference (markdown), generated from the schema."""
    rows = schema_fields()
    stale = sorted(set(MEANINGS) - {row.path for row in rows})
    if stale:
        raise MissingDocError(f"MEANINGS documents keys the schema no longer has: {', '.join(stale)}")
    scenario_from_dict(yaml.safe_load(EXAMPLE), source="docgen.EXAMPLE")
    lines = [
        "# Scenario file reference",
        "",
        "<!-- generated by `python -m swarmpc.docgen` from swarmpc/config.py; do not edit by hand -->",
        "",
        "A scenario is a YAML mapping (`swarmpc run FILE.yaml`, `swarmpc.config.load_scenario`) or a",
        "dict (`swarmpc.config.scenario_from_dict`). Every key but `agents` has a default; unknown keys are",
        "an error. `[]` in a path marks the items of a list. A run folder's `scenario.yaml` is the",
        "scenario with every default filled in.",
        "",
        "```yaml",
        EXAMPLE.rstrip(),
        "```",
        "",
        "| key | type | default | meaning |",
        "|---|---|---|---|",
    ]
    for row in rows:
        lines.append(f"| `{row.path}` | {_cell(row.type)} | {_cell(row.default)} | {_cell(row.meaning)} |")
    lines += ["", "## Validation", "", RULES.rstrip(), ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------------- CLI
def _param_type(param: Any, ctx: Any) -> str:
    """The parameter's type as the help screen shows it (choices spelled out)."""
    if getattr(param, "is_flag", False):
        return "flag"
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:  # typer >= 0.2x (its own parameter classes)
        if descriptor.is_choice:
            return " \\| ".join(str(getattr(c, "value", c)) for c in descriptor.choices or ())
        try:
            return str(param.display_type(ctx)).strip("<>")
        except Exception:  # noqa: BLE001 - fall back to the annotation's name
            return param.bare_type()
    click_type = getattr(param, "type", None)  # click parameters
    choices = getattr(click_type, "choices", None)
    if choices:
        return " \\| ".join(str(getattr(c, "value", c)) for c in choices)
    return str(getattr(click_type, "name", "text")).lower()


def _param_default(param: Any) -> str:
    default = param.default
    if getattr(param, "required", False):
        return "required"
    if default is None:
        return "–"
    if isinstance(default, enum.Enum):
        default = default.value
    if isinstance(default, bool):
        return "off" if not default else "on"
    return f"`{default}`"


def cli_reference() -> str:
    """The command-line reference (markdown), generated from the typer app."""
    import typer

    from swarmpc.cli import app

    group = typer.main.get_command(app)
    assert isinstance(group, typer.core.TyperGroup)  # an app of several commands is a group
    root = group.make_context("swarmpc", [], resilient_parsing=True)
    lines = [
        "# Command-line reference",
        "",
        "<!-- generated by `python -m swarmpc.docgen` from swarmpc/cli.py; do not edit by hand -->",
        "",
        f"`swarmpc COMMAND [ARGS] [OPTIONS]`: {group.help}",
        "",
        "Every command takes `--help`. Bad input (an unknown scenario, a scenario field out of range, a",
        "missing run folder, a bad option value) prints one line `swarmpc: error: ...` on stderr and exits",
        "with status 2, writing nothing.",
        "",
    ]
    own = [p for p in group.params if not getattr(p, "hidden", False)]
    if own:
        lines += ["Options of `swarmpc` itself, before the command (`swarmpc --version`):", ""]
        lines += _param_table(own, root)
    for name, command in group.commands.items():
        ctx = command.make_context(name, [], parent=root, resilient_parsing=True)
        params = [p for p in command.params if not getattr(p, "hidden", False)]
        usage = [f"swarmpc {name}"]
        for param in params:
            if getattr(param, "param_type_name", "") == "argument":
                usage.append(param.name.upper() if param.required else f"[{param.name.upper()}]")
        if any(getattr(p, "param_type_name", "") == "option" for p in params):
            usage.append("[OPTIONS]")
        lines += [f"## `swarmpc {name}`", "", (command.help or "").strip(), "", "```", " ".join(usage), "```", ""]
        if params:
            lines += _param_table(params, ctx)
    return "\n".join(lines)


def _param_table(params: list[Any], ctx: Any) -> list[str]:
    """A markdown table of command-line parameters (type, default, help), then a blank line."""
    lines = ["| parameter | type | default | meaning |", "|---|---|---|---|"]
    for param in params:
        if getattr(param, "param_type_name", "") == "argument":
            flags = f"`{param.name.upper()}`"
        else:
            flags = ", ".join(f"`{opt}`" for opt in [*param.opts, *param.secondary_opts])
        help_text = getattr(param, "help", None) or ""
        lines.append(f"| {flags} | {_param_type(param, ctx)} | {_cell(_param_default(param))} | {_cell(help_text)} |")
    return [*lines, ""]


# ----------------------------------------------------------------------------------- run folder
RUN_FOLDER_INTRO = """\
A run folder is what `swarmpc run` (or `write_run(result, DIR)` of `swarmpc.simulation.results`)
writes: the files below, in a folder written under a temporary name and moved into place when
complete. `swarmpc.simulation.rundata.load_run(DIR)` reads it back (checked, as read-only arrays);
plain `json` and `numpy.load` read it too. Numbers are SI: metres, seconds.

Shapes use **T** (closed-loop steps taken, `summary.json` `steps`), **M** (agents), **d** (spatial
dimension, 2 or 3) and **I** (the most ADMM iterations of any step). Positions come first in a
state, velocities after: a state is [p, v] with 2d entries. The *present* column says when an
entry is there:
"""


def _condition_table() -> list[str]:
    rows = (f"| `{code}` | {_cell(text)} |" for code, text in CONDITIONS.items())
    return ["| present | meaning |", "|---|---|", *rows]


def _file_tables() -> list[str]:
    """The files table, the summary keys and one table per archive."""
    lines = ["## Files", "", "| file | present | content |", "|---|---|---|"]
    lines += [f"| {', '.join(f'`{n}`' for n in f.name.split(', '))} | `{f.when}` | {_cell(f.meaning)} |" for f in FILES]
    lines += ["", "## `summary.json`", "",
              "A JSON object; dotted keys are nested (`step_time_ms.median`). "
              "Non-finite numbers are written as `null`.",
              "", "| key | type | units | present | meaning |", "|---|---|---|---|---|"]
    lines += [f"| `{k.key}` | {_cell(k.type)} | {k.units} | `{k.when}` | {_cell(k.meaning)} |" for k in SUMMARY_KEYS]
    for archive in dict.fromkeys(a.file for a in ARRAYS):
        lines += ["", f"## `{archive}`", "", "| array | shape | dtype | units | present | meaning |",
                  "|---|---|---|---|---|---|"]
        lines += [
            f"| `{a.name}` | {a.shape} | {a.dtype} | {a.units} | `{a.when}` | {_cell(a.meaning)} |"
            for a in ARRAYS if a.file == archive
        ]
    return [*lines, ""]


def _column_label(name: str) -> str:
    """A CSV column of :data:`swarmpc.export.CSV_COLUMNS`, ``{axis}`` spelled out per axis."""
    if "{axis}" not in name:
        return f"`{name}`"
    return ", ".join(f"`{name.format(axis=axis)}`" for axis in "xyz")


def _export_tables() -> list[str]:
    """The CSV columns, the MCAP topics and the ``/metrics`` fields of ``swarmpc export``."""
    from swarmpc.export import CSV_COLUMNS, FRAME_ID, MCAP_TOPICS, METRICS, csv_header

    lines = [
        "## Exports (`swarmpc export`)", "",
        "`swarmpc export RUN_DIR --format csv|mcap` writes `RUN_DIR/run.csv` or `RUN_DIR/run.mcap` (or `--out`).",
        "", "### CSV", "",
        "One header row, then one row per state k and agent i, numbers in full precision (they read back",
        "exactly). A 2D run has no `z` columns:", "",
        "```", ",".join(csv_header(2)), ",".join(csv_header(3)), "```", "",
        "| column | units | meaning |", "|---|---|---|",
        *(f"| {_column_label(c.name)} | {c.units} | {_cell(c.meaning)} |" for c in CSV_COLUMNS),
        "", "### MCAP (Foxglove)", "",
        "Open the file in Foxglove (*Open local file*), add a 3D panel (the scene is in the frame",
        f"`{FRAME_ID}`, in metres) and a Plot panel for `/metrics`. Time stamps are `t` in nanoseconds (the",
        "run starts at 0). Scenes are `foxglove.SceneUpdate` messages (protobuf; the schema is embedded);",
        "an entity replaces the entity of the same id from the topic's previous message.", "",
        "| topic | schema | messages | content |", "|---|---|---|---|",
        *(f"| `{t.topic}` | `{t.schema}` | {t.messages} | {_cell(t.meaning)} |" for t in MCAP_TOPICS),
        "", "Fields of the `/metrics` messages (JSON):", "",
        "| field | type | units | meaning |", "|---|---|---|---|",
        *(f"| `{m.name}` | {m.type} | {m.units} | {_cell(m.meaning)} |" for m in METRICS),
    ]
    return [*lines, ""]


def run_folder_reference() -> str:
    """The run-folder reference (markdown), generated from :mod:`swarmpc.simulation.contract`
    and the export tables of :mod:`swarmpc.export`."""
    lines = [
        "# Run folder reference",
        "",
        (
            "<!-- generated by `python -m swarmpc.docgen` from swarmpc/simulation/contract.py and "
            "swarmpc/export.py; do not edit by hand -->"
        ),
        "",
        RUN_FOLDER_INTRO.rstrip(),
        "",
        *_condition_table(),
        "",
        *_file_tables(),
        *_export_tables(),
    ]
    return "\n".join(lines).rstrip("\n") + "\n"


def write_all(docs: Path) -> list[Path]:
    """Write every reference page into ``docs``; returns the written files."""
    pages = {
        "scenario-reference.md": scenario_reference(),
        "cli-reference.md": cli_reference(),
        "run-folder-reference.md": run_folder_reference(),
    }
    written = []
    for filename, text in pages.items():
        path = docs / filename
        path.write_text(text)
        written.append(path)
    return written


def main(argv: list[str]) -> int:
    if argv == ["--write"]:
        root = Path(__file__).resolve().parents[2]
        for path in write_all(root / "docs"):
            print(path)
        return 0
    if argv == ["--cli"]:
        sys.stdout.write(cli_reference())
        return 0
    if argv == ["--run-folder"]:
        sys.stdout.write(run_folder_reference())
        return 0
    if argv:
        print("usage: python -m swarmpc.docgen [--cli | --run-folder | --write]", file=sys.stderr)
        return 2
    sys.stdout.write(scenario_reference())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

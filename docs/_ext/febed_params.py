"""Sphinx directive `febed-params`: the case-file reference, generated from `febed.schema` at build time.

Every `Param` of `febed.schema.SCHEMA` (one table per section) and of `febed.schema.BOUNDARY` (the
`[gas.boundary.<tag>]` tables) becomes one row: key, default, unit, allowed values and description. The
allowed values are `Param.allowed()`, the same text the case validation prints, so this page, `febed
params` and the error messages cannot disagree.

Usage in a MyST page::

    ```{febed-params}
    ```

    ```{febed-params} contact
    ```

With no argument it writes every section, each under its own heading; with a section name (or
`gas.boundary`) only that table.
"""

from __future__ import annotations

import math

from docutils import nodes
from docutils.parsers.rst import Directive, directives

from febed.schema import BOUNDARY, SCHEMA, Param

BOUNDARY_SECTION = "gas.boundary.<tag>"
COLUMNS = (("key", 16), ("default", 14), ("unit", 8), ("allowed", 24), ("description", 38))

SECTION_INTRO = {
    "run": "What is solved and for how long; the run's failure limits.",
    "mesh": "The mesh: a gmsh file with named physical groups, or a built-in geometry.",
    "gas": "Gas properties, the VANS solver and its time step.",
    BOUNDARY_SECTION: (
        "One table per facet tag of the mesh, e.g. `[gas.boundary.inlet]`. A case that sets any boundary table "
        "sets one for every tag; a case that sets none has walls with the porous wall law on every tag."
    ),
    "particles": "The original particles (before any coarse-graining) and how the bed is made.",
    "contact": "The contact law, its parameters and the DEM time step.",
    "coupling": "Drag closure, pressure-gradient force, neighbour filter.",
    "coarse_grain": "What is simulated in place of the original particles.",
    "prescribed_gas": 'One-way runs (`run.mode = "one-way"`): the gas velocity field the particles move in.',
    "output": "Where and how often febed writes fields, particles, probes and checkpoints.",
}


def format_default(par: Param) -> str:
    """The default as it would be written in a case file ("unset" for a value derived at run time)."""
    value = par.default
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return "inf" if math.isinf(value) else f"{value:g}"
    if isinstance(value, list):
        return "[" + ", ".join(format_default_item(v) for v in value) + "]"
    return str(value)


def format_default_item(value) -> str:
    """One item of a list default."""
    if isinstance(value, float):
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return f"{value:g}"
    return f'"{value}"' if isinstance(value, str) else str(value)


def _paragraph(text: str, literal: bool = False) -> nodes.paragraph:
    para = nodes.paragraph()
    para += nodes.literal(text, text) if literal else nodes.Text(text)
    return para


def _row(cells: list[nodes.Node]) -> nodes.row:
    row = nodes.row()
    for cell in cells:
        entry = nodes.entry()
        entry += cell
        row += entry
    return row


def param_table(section: str, params: dict[str, Param]) -> nodes.table:
    """A docutils table of one section's parameters."""
    table = nodes.table(classes=["febed-params"])
    group = nodes.tgroup(cols=len(COLUMNS))
    table += group
    for _, width in COLUMNS:
        group += nodes.colspec(colwidth=width)
    head = nodes.thead()
    head += _row([_paragraph(name) for name, _ in COLUMNS])
    group += head
    body = nodes.tbody()
    for key, par in params.items():
        unit = "" if par.unit in ("", "-") else par.unit
        body += _row(
            [
                _paragraph(key, literal=True),
                _paragraph(format_default(par), literal=True),
                _paragraph(unit),
                _paragraph(par.allowed()),
                _paragraph(par.help),
            ]
        )
    group += body
    return table


def all_sections() -> dict[str, dict[str, Param]]:
    """Every table of a case file in the order a case file has them, boundary tables after `[gas]`."""
    out: dict[str, dict[str, Param]] = {}
    for name, params in SCHEMA.items():
        out[name] = params
        if name == "gas":
            out[BOUNDARY_SECTION] = BOUNDARY
    return out


class FebedParams(Directive):
    """Insert the parameter tables of the case schema (all sections, or the one named)."""

    optional_arguments = 1
    has_content = False
    option_spec = {"no-headings": directives.flag}

    def run(self) -> list[nodes.Node]:
        """Build the tables; an unknown section name is a build error naming the valid ones."""
        sections = all_sections()
        if self.arguments:
            name = self.arguments[0]
            if name == "gas.boundary":
                name = BOUNDARY_SECTION
            if name not in sections:
                raise self.error(f"febed-params: unknown section {name!r}; valid: {', '.join(sections)}")
            return [param_table(name, sections[name])]
        out: list[nodes.Node] = []
        env = self.state.document.settings.env
        for name, params in sections.items():
            section_id = "params-" + name.replace(".", "-").replace("<", "").replace(">", "").replace("_", "-")
            section = nodes.section(ids=[section_id])
            title = f"[{name}]"
            section += nodes.title(title, "", nodes.literal(title, title))
            intro = SECTION_INTRO.get(name)
            if intro:
                para = nodes.paragraph()
                text_nodes, messages = self.state.inline_text(intro, self.lineno)
                para += text_nodes
                section += para
                section += messages
            section += param_table(name, params)
            env.note_reread()  # the schema lives in code: rebuild this page on every build
            out.append(section)
        return out


def setup(app):
    """Register the directive."""
    app.add_directive("febed-params", FebedParams)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}

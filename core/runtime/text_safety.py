"""Text from inputs made safe for the files QuakeScan writes: one helper per kind of output.

Footprint IDs and attributes, file names and CRS names come from somebody else: a cadastre,
a colleague's drive, a hostile sender. Each output reads text its own way, so each gets the
escaping it needs, here and nowhere else:

- CSV: a cell a spreadsheet would run as a formula (it begins with = + - @, TAB or CR) gets
  a leading single quote, as OWASP's "CSV injection" advice says (`spreadsheet_cell`;
  `spreadsheet_raw` undoes it); any cell holding a comma, quote, CR or LF is quoted
  (`csv_line`: Python's csv module leaves a bare CR unquoted when the line ends in LF,
  and a reader then splits the row there).
- JSON: strict (`json_text`): NaN and infinities, which JSON does not have, are null.
- HTML: `html_text` for text between tags and in attributes; `script_json` for JSON inside
  a <script> element, where `</script>` or `<!--<script>` in a string would end the script
  or stop it from ending (`<`, `>` and `&` as \\u escapes, which JSON reads as themselves).
- JavaScript numbers: `js_safe_id`, integers beyond 2^53 as text (a double rounds them).
- Any text file: `utf8_text`, a lone surrogate (a JSON "\\ud800", a file name that is not
  UTF-8) as its backslash escape, since UTF-8 cannot encode it.

Standard library only (the Blender scripts import `quakescan.runtime`).
"""
from __future__ import annotations

import html
import json
import math

FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")  # OWASP: what a spreadsheet takes as a formula
FORMULA_ESCAPE = "'"
JS_SAFE_INTEGER = 2 ** 53 - 1  # Number.MAX_SAFE_INTEGER: beyond it a double cannot hold every integer


def utf8_text(text) -> str:
    """`text` as a str UTF-8 can encode: lone surrogates become their backslash escape
    ("\\ud800"); every other character is kept."""
    text = str(text)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def spreadsheet_cell(text) -> str:
    """A CSV cell of user text that no spreadsheet runs as a formula: a leading single quote
    before a text that begins with one of `FORMULA_STARTS` (after any quotes of its own, so
    that `spreadsheet_raw` gives back exactly the text: "'=x" is written "''=x")."""
    text = utf8_text(text)
    if text.lstrip(FORMULA_ESCAPE).startswith(FORMULA_STARTS):
        return FORMULA_ESCAPE + text
    return text


def spreadsheet_raw(cell: str) -> str:
    """The text `spreadsheet_cell` escaped (a cell without its escape is returned as it is)."""
    if cell.startswith(FORMULA_ESCAPE) and cell.lstrip(FORMULA_ESCAPE).startswith(FORMULA_STARTS):
        return cell[1:]
    return cell


def csv_cell(value) -> str:
    """One field of a CSV line (RFC 4180): quoted, its quotes doubled, when it holds a comma,
    a quote, a CR or an LF; as it is otherwise (the bytes of Python's csv module with
    lineterminator "\\n", except that a bare CR is quoted too)."""
    text = utf8_text(value)
    if any(c in text for c in ',"\r\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def csv_line(cells) -> str:
    """A CSV line of `cells` (str), ending in LF."""
    return ",".join(csv_cell(c) for c in cells) + "\n"


def finite_json(doc):
    """`doc` with every float that is not finite (NaN, ±infinity) as None, through dicts,
    lists and tuples (anything else is left to the encoder)."""
    if isinstance(doc, float):
        return doc if math.isfinite(doc) else None
    if isinstance(doc, dict):
        return {k: finite_json(v) for k, v in doc.items()}
    if isinstance(doc, (list, tuple)):
        return [finite_json(v) for v in doc]
    return doc


def json_text(doc, **dumps_kwargs) -> str:
    """Strict JSON of `doc`: NaN and infinities as null, never the `NaN` that Python's json
    writes by default and other readers refuse. `default` (for objects json does not know)
    is applied first and its result made finite too."""
    default = dumps_kwargs.pop("default", None)
    if default is not None:
        def finite_default(o):
            return finite_json(default(o))

        dumps_kwargs["default"] = finite_default
    dumps_kwargs.pop("allow_nan", None)
    return json.dumps(finite_json(doc), allow_nan=False, **dumps_kwargs)


def html_text(value) -> str:
    """`value` as HTML text, for between tags and inside quoted attributes."""
    return html.escape(utf8_text(value), quote=True)


def script_json(doc, **dumps_kwargs) -> str:
    """Strict JSON (`json_text`) that can stand inside an HTML <script> element: `<`, `>` and
    `&` (which occur only inside JSON strings) as \\u escapes, so no text can close the
    element (`</script>`) or open a comment that keeps it from closing (`<!--<script>`);
    JavaScript reads the same strings."""
    text = json_text(doc, **dumps_kwargs)
    return (text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
            .replace("\u2028", "\\u2028").replace("\u2029", "\\u2029"))


def js_safe_id(value: int):
    """An integer ID as a JavaScript page must carry it: the number while a double holds it
    exactly, its decimal text beyond 2^53 (the Dutch register's IDs fit; a 19-digit one
    does not)."""
    value = int(value)
    return value if abs(value) <= JS_SAFE_INTEGER else str(value)


__all__ = ["FORMULA_ESCAPE", "FORMULA_STARTS", "JS_SAFE_INTEGER", "csv_cell", "csv_line", "finite_json",
           "html_text", "js_safe_id", "json_text", "script_json", "spreadsheet_cell", "spreadsheet_raw",
           "utf8_text"]

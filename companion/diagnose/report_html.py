"""One self-contained HTML page of a diagnosis (``diagnose --report DIR`` writes ``DIR/report.html``).

The page is the Markdown report of the same run (``report.md``, with its PNG plots beside it)
turned into HTML, the plots embedded as base64 PNG, so it opens offline and travels as one
file; nothing on it is loaded from elsewhere. Above the evidence comes the first line in plain
words (``companion.diagnose.advice.lead``: what differs, how sure, what to change in the config with the
suggested values) and the config changes as TOML ready to paste.

Both diagnose modes use it: the closed-loop finder (``companion.diagnose.closed_loop.command``) and the sensor-only
diagnosis (``companion.diagnose.sensor.api``). It reads only the report and the files written beside
it, so the content stays the Markdown writers'.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

from companion.diagnose.advice import config_changes, lead
from companion.diagnose.report import Report
from companion.errors import FlowholdError

_CSS = """body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;padding:0 1em;color:#222;
line-height:1.45}h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
h3{font-size:1.05em}table{border-collapse:collapse;font-size:.85em;margin:.5em 0}td,th{border:1px solid #ddd;
padding:3px 6px;text-align:left;vertical-align:top}th{background:#f4f4f4}.lead{font-size:1.12em;
background:#f5f8ff;border-left:4px solid #36c;padding:.6em 1em}pre{background:#f6f6f6;padding:.6em 1em;
overflow-x:auto}code{background:#f3f3f3;padding:0 .2em}img{max-width:100%}figure{margin:1em 0}
figcaption{font-size:.85em;color:#555}"""

_IMAGE = re.compile(r"^!\[(?P<alt>[^\]]*)\]\((?P<src>[^)\s]+)\)$")
_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")
_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*([^*]+)\*\*")
_ITALIC = re.compile(r"(?<![\w*])\*([^*\s][^*]*?)\*(?![\w*])")


def _inline(text: str) -> str:
    """Markdown's inline marks in one line of text, HTML-escaped. Links become their text and
    their target in brackets: the page loads nothing and points nowhere it cannot be read."""
    out = html.escape(text, quote=False)
    out = _LINK.sub(lambda m: f"{m.group(1)} ({m.group(2)})", out)
    out = _CODE.sub(lambda m: f"<code>{m.group(1)}</code>", out)
    out = _BOLD.sub(lambda m: f"<strong>{m.group(1)}</strong>", out)
    return _ITALIC.sub(lambda m: f"<em>{m.group(1)}</em>", out)


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _image(alt: str, src: str, folder: Path) -> str:
    path = folder / src
    if src.startswith(("http:", "https:", "//")) or not path.is_file():
        return f"<p>[plot not found: {html.escape(src)}]</p>"
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(alt)}</figcaption></figure>")


def markdown_to_html(text: str, folder: Path) -> str:
    """The subset of Markdown the reports use (headings, paragraphs, lists, tables, code blocks,
    images alone on a line), as HTML; images are read from ``folder`` and embedded."""
    out: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        s = line.strip()
        if not s:
            i += 1
            continue
        if s.startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].strip().startswith("```"):
                j += 1
            out.append("<pre>" + html.escape("\n".join(lines[i + 1:j])) + "</pre>")
            i = j + 1
            continue
        m = re.match(r"^(#{1,6})\s+(.*)$", s)
        if m:
            k = len(m.group(1))
            out.append(f"<h{k}>{_inline(m.group(2))}</h{k}>")
            i += 1
            continue
        m = _IMAGE.match(s)
        if m:
            out.append(_image(m.group("alt"), m.group("src"), folder))
            i += 1
            continue
        if s.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].strip().startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            def rule(r: list[str]) -> bool:
                return all(re.fullmatch(r":?-{3,}:?", c) for c in r)

            head = rows[0] if len(rows) > 1 and rule(rows[1]) else None
            rest = [r for r in (rows[2:] if head is not None else rows) if not rule(r)]
            table = ["<table>"]
            if head is not None:
                table.append("<tr>" + "".join(f"<th>{_inline(c)}</th>" for c in head) + "</tr>")
            table += ["<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in rest]
            out.append("".join(table) + "</table>")
            continue
        if re.match(r"^[-*]\s+", s):
            items = []
            while i < len(lines) and re.match(r"^\s*[-*]\s+", lines[i]):
                item = re.sub(r"^\s*[-*]\s+", "", lines[i])
                i += 1
                while i < len(lines) and lines[i].startswith("  ") and lines[i].strip() \
                        and not re.match(r"^\s*[-*]\s+", lines[i]):
                    item += " " + lines[i].strip()
                    i += 1
                items.append(f"<li>{_inline(item)}</li>")
            out.append("<ul>" + "".join(items) + "</ul>")
            continue
        para = [s]
        i += 1
        while i < len(lines) and lines[i].strip() and not re.match(r"^(#{1,6}\s|\||[-*]\s|```|!\[)",
                                                                   lines[i].strip()):
            para.append(lines[i].strip())
            i += 1
        out.append(f"<p>{_inline(' '.join(para))}</p>")
    return "\n".join(out)


def render(report: Report, markdown: str, folder: Path, *, q_rad_per_count: float) -> str:
    """The whole page: title, the plain-words first line, the config changes, then the evidence
    (``markdown``, the report's Markdown, with its images read from ``folder``)."""
    md_lines = markdown.splitlines()
    title = report.recording
    if md_lines and md_lines[0].startswith("# "):
        title = md_lines[0][2:].strip()
        md_lines = md_lines[1:]
    first = lead(report, q_rad_per_count=q_rad_per_count)
    changes = config_changes(report, q_rad_per_count=q_rad_per_count)
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{_inline(title)}</h1>", refly_section(folder),
             f'<p class="lead" id="headline">{html.escape(first)}</p>']
    if changes:
        parts.append("<p>The same changes as TOML, the fitted values: in a copy of the config, set these keys in "
                     "the tables of the same name (an <code>[effects.*]</code> table is added whole). Every key is "
                     "described in docs/reference.md and docs/diagnose.md.</p>")
        parts.append("<pre>" + html.escape("\n\n".join(f"# {c.why}\n{c.toml()}" for c in changes)) + "</pre>")
    parts.append(autopilot_actions_html(report))
    parts += ["<h2>The evidence</h2>", markdown_to_html("\n".join(md_lines), folder), "</body></html>", ""]
    return "\n".join(parts)


def autopilot_actions_html(report: Report) -> str:
    """The autopilot parameters the report's ``actions`` suggest, as a table ("" when none)."""
    rows = [a for a in report.actions if a.system in ("ardupilot", "px4")]
    if not rows:
        return ""
    cells = "".join(f"<tr><td>{html.escape(a.system)}</td><td><code>{html.escape(a.parameter)}</code></td>"
                    f"<td>{a.value:.6g}</td><td>{a.sigma:.2g}</td><td>{html.escape(a.unit)}</td>"
                    f"<td>{html.escape(a.because)}</td><td>{html.escape(a.note)}</td></tr>" for a in rows)
    return ("<p>On the autopilot, set (the fitted value, its 1-sigma uncertainty; docs/diagnose.md says how each "
            "is computed from the autopilot's own source):</p><table><tr><th>autopilot</th><th>parameter</th>"
            "<th>value</th><th>sigma</th><th>unit</th><th>because</th><th>note</th></tr>" + cells + "</table>")


def write_html_report(report: Report, markdown_path: str | Path, *, q_rad_per_count: float) -> Path:
    """Write ``report.html`` beside ``markdown_path`` (the run's ``report.md`` and its PNGs);
    returns its path."""
    md = Path(markdown_path)
    out = md.with_name("report.html")
    try:
        out.write_text(render(report, md.read_text(), md.parent, q_rad_per_count=q_rad_per_count))
    except OSError as exc:
        raise FlowholdError(f"cannot write the HTML report {out}: {exc.strerror}") from None
    return out


#: what ``python -m simvehicle refly --report DIR`` writes into DIR: "your simulation vs your flight,
#: before and after", the first thing on the page of a diagnosis written to the same folder
REFLY_MD = "refly.md"
_REFLY_SECTION = re.compile(r'<section id="refly">.*?</section>', re.S)


def refly_section(folder: Path) -> str:
    """The refly comparison in ``folder`` (``REFLY_MD`` and its plots) as one HTML section; "" when
    there is none."""
    md = Path(folder) / REFLY_MD
    if not md.is_file():
        return ""
    return '<section id="refly">' + markdown_to_html(md.read_text(), Path(folder)) + "</section>"


def write_refly_html(markdown_path: str | Path) -> Path:
    """``report.html`` beside refly's Markdown: a diagnosis page already there gets the comparison
    first (under its title, replacing an older one); otherwise a page of its own."""
    md = Path(markdown_path)
    out = md.with_name("report.html")
    section = refly_section(md.parent)
    try:
        if out.is_file():
            text = _REFLY_SECTION.sub("", out.read_text())
            i = text.find("</h1>")
            if i >= 0:
                out.write_text(text[:i + 5] + section + text[i + 5:])
                return out
        title = "Your simulation vs your flight"
        out.write_text("\n".join(["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
                                  f"<title>{title}</title><style>{_CSS}</style></head><body>",
                                  f"<h1>{title}</h1>", section, "</body></html>", ""]))
    except OSError as exc:
        raise FlowholdError(f"cannot write the HTML report {out}: {exc.strerror}") from None
    return out

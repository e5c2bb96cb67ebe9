"""One HTML page per run (``crisp reconstruct``, ``crisp eval``, ``crisp gap diagnose``): its numbers,
plots and video, written beside the files it shows, to open in a browser.

A page is a list of :class:`Section` s: a table of named values, figures and videos (file names
relative to the page; missing ones are left out), or HTML made from Markdown. The page needs no
network and no script to show its content; a small inline script only records in ``<body
data-images="loaded/total" data-videos="loaded/total" data-image-boxes="x,y,w,h;...">`` what the
browser could load and where it drew the images, which the tests read from a real headless browser.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import markdown
from jinja2 import Environment, select_autoescape

from crisp_gym.atomic import write_text

_PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{{ title }}</title>
<style>
 body { font-family: system-ui, sans-serif; margin: 2rem auto; max-width: 70rem; color: #222; line-height: 1.4; }
 h1 { margin-bottom: 0.2rem; } .subtitle { color: #666; margin-top: 0; }
 table { border-collapse: collapse; margin: 0.5rem 0 1rem; } td, th { border: 1px solid #ccc; padding: 0.2rem 0.6rem; }
 td:first-child { color: #555; } figure { display: inline-block; margin: 0.5rem; } img, video { max-width: 100%; }
 figcaption { color: #666; font-size: 0.9rem; }
</style>
</head>
<body>
<h1>{{ title }}</h1>
{% if subtitle %}<p class="subtitle">{{ subtitle }}</p>{% endif %}
{% for section in sections %}
<h2>{{ section.title }}</h2>
{% if section.rows %}<table>
{% for key, value in section.rows %}<tr><td>{{ key }}</td><td>{{ value }}</td></tr>
{% endfor %}</table>{% endif %}
{% if section.html %}{{ section.html | safe }}{% endif %}
{% for figure in section.figures %}
<figure><img src="{{ figure }}" alt="{{ figure }}"><figcaption>{{ figure }}</figcaption></figure>
{% endfor %}
{% for video in section.videos %}
<figure><video src="{{ video }}" controls loop muted preload="metadata"></video>
<figcaption>{{ video }}</figcaption></figure>
{% endfor %}
{% endfor %}
<script>
 function count() {
   const images = [...document.images], videos = [...document.querySelectorAll("video")];
   document.body.dataset.images = images.filter(i => i.complete && i.naturalWidth > 0).length + "/" + images.length;
   const played = videos.filter(v => v.readyState >= 1 && v.videoWidth > 0);
   document.body.dataset.videos = played.length + "/" + videos.length;
   document.body.dataset.imageBoxes = images.map(i => { const r = i.getBoundingClientRect();
     return [r.left + scrollX, r.top + scrollY, r.width, r.height].map(Math.round).join(","); }).join(";");
 }
 document.querySelectorAll("img").forEach(i => i.addEventListener("load", count));
 document.querySelectorAll("video").forEach(v => v.addEventListener("loadedmetadata", count));
 window.addEventListener("load", count);
</script>
</body>
</html>
"""


@dataclass(frozen=True)
class Section:
    """Part of a page: a table of ``rows`` (name, value), ``figures`` and ``videos`` (file names
    beside the page), or ``html`` already made (see :func:`markdown_section`)."""

    title: str
    rows: tuple[tuple[str, str], ...] = ()
    figures: tuple[str, ...] = ()
    videos: tuple[str, ...] = ()
    html: str = field(default="", repr=False)


def rows_from(values: Mapping[str, Any], digits: int = 3, depth: int = 1) -> tuple[tuple[str, str], ...]:
    """Table rows of the scalars of ``values``, floats with ``digits`` significant digits; mappings
    nested up to ``depth`` levels are flattened as ``outer / inner`` (deeper ones, lists and arrays
    are left out: per-frame diagnostics belong in the JSON, not the page)."""
    rows = []
    for key, value in values.items():
        if isinstance(value, Mapping):
            if depth > 0:
                rows += [(f"{key} / {k}", v) for k, v in rows_from(value, digits, depth - 1)]
        elif isinstance(value, bool) or value is None or isinstance(value, (str, int)):
            rows.append((str(key), str(value)))
        elif isinstance(value, float):
            rows.append((str(key), f"{value:.{digits}g}"))
    return tuple(rows)


def markdown_section(title: str, text: str) -> Section:
    """A section from Markdown (tables and images included)."""
    return Section(title=title, html=markdown.markdown(text, extensions=["tables"]))


def write_html_report(path: str | Path, title: str, sections: Iterable[Section], subtitle: str = "") -> Path:
    """Write the page atomically; figures and videos that do not exist beside it are left out."""
    path = Path(path)
    present = [Section(s.title, s.rows, tuple(f for f in s.figures if (path.parent / f).is_file()),
                       tuple(v for v in s.videos if (path.parent / v).is_file()), s.html) for s in sections]
    page = Environment(autoescape=select_autoescape(default=True)).from_string(_PAGE)
    return write_text(path, page.render(title=title, subtitle=subtitle, sections=present))

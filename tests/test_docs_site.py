"""The documentation site builds with ``mkdocs build --strict`` (a broken link, anchor, missing page
or unresolvable API reference fails), works offline (nothing loaded from another host, the math
included), its API pages show no raw Sphinx role, and the README stays the short front page it is
meant to be."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site, built once for this module's tests with ``mkdocs build --strict``."""
    try:
        import mkdocs  # noqa: F401
        import mkdocstrings  # noqa: F401
    except ImportError:  # pragma: no cover
        pytest.fail("the docs extra is not installed: run the README's test command (it installs .[docs])")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    site = tmp_path_factory.mktemp("docs") / "site"
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(site)], cwd=ROOT,
                       capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 0, p.stderr[-4000:]
    return site


def test_the_site_builds_strictly_and_loads_nothing_from_another_host(site):
    # pages are NAME.html (the offline plugin turns directory URLs off, so that links work from disk)
    for page in ("index.html", "environment.html", "protocol.html", "results.html", "model.html",
                 "notation.html", "extending.html", "training.html", "certificate.html", "api/env.html"):
        assert (site / page).is_file(), page
    # the API reference was rendered from the docstrings, not left as a ::: directive
    api = (site / "api" / "env.html").read_text()
    assert "PlanarBLFEnv" in api and ":::" not in api
    # the generated tables reached the site
    assert "control_period" in (site / "environment.html").read_text()
    # offline: no script, stylesheet, font or image from another host
    external = re.compile(r"""<(?:script|link|img)\b[^>]*\b(?:src|href)=["'](?:https?:)?//""", re.I)
    offenders = [str(f.relative_to(site)) for f in site.rglob("*.html") if external.search(f.read_text())]
    assert not offenders, offenders
    assert not any("fonts.googleapis" in f.read_text() for f in site.rglob("*.html"))
    # opened from disk, search reads its index from a script and runs its worker through the site's own
    # copy of the iframe-worker shim (the offline plugin would otherwise add one from another host)
    assert (site / "search" / "search_index.js").is_file()
    assert 'src="assets/javascripts/iframe-worker/shim.js"' in (site / "index.html").read_text()
    # nor from the project's own stylesheets (url() and @import)
    css_external = re.compile(r"""(?:url\(\s*["']?|@import\s+["']?)(?:https?:)?//""", re.I)
    assert not [str(f.relative_to(site)) for f in (site / "stylesheets").rglob("*.css")
                if css_external.search(f.read_text())]


ROLE = re.compile(r":(?:py:)?(?:func|meth|class|attr|data|const|mod|exc|obj|type):(?:`|<code>)")


def test_the_api_pages_show_no_raw_restructuredtext_role(site):
    """Sphinx roles in docstrings (:func:`x` ...) render as code, linked where the target is documented
    (docs/griffe_roles.py), never as ":func:" followed by the name."""
    pages = sorted((site / "api").rglob("*.html"))
    assert pages
    raw = [f"{f.relative_to(site)}: {m.group(0)}" for f in pages for m in ROLE.finditer(f.read_text())]
    assert not raw, raw
    blocks = (site / "api" / "blocks.html").read_text()
    # a documented target is a link: registry.py's :class:`~blf_gym.plugins.blocks.Observer` ...
    assert re.search(r'<a class="autorefs[^"]*"[^>]*href="#blf_gym\.plugins\.blocks\.Observer"[^>]*><code>Observer</code></a>',
                     blocks)
    # ... and one the API pages do not document is plain code (its module has no page)
    assert re.search(r'<span title="blf_gym\.plugins\.blocks"><code>blf_gym\.plugins\.blocks</code></span>', blocks)
    # double backticks were code already, and none is left raw
    assert "<code>leso</code>" in blocks and not any("``" in f.read_text() for f in pages)


def test_math_is_mathml_made_at_build_time_and_needs_no_other_host(site):
    """TeX math becomes MathML when the site is built (docs/mathml_hook.py): no MathJax or KaTeX script,
    and the math font is served by the site itself."""
    notation = (site / "notation.html").read_text()
    assert notation.count("<math") >= 10 and 'display="block"' in notation
    assert "arithmatex" not in notation and "\\(" not in notation and "\\[" not in notation
    assert "MathML\"" not in notation  # the namespace (a name, not a download) is left out: HTML needs none
    scripts = re.compile(r"<script\b[^>]*\bsrc=[\"'][^\"']*(?:mathjax|katex)", re.I)
    assert not [str(f.relative_to(site)) for f in site.rglob("*.html") if scripts.search(f.read_text())]
    css = (site / "stylesheets" / "extra.css").read_text()
    fonts = re.findall(r"""url\(\s*["']?([^"')]+)""", css)
    assert fonts and all(not re.match(r"(?:[a-z]+:)?//", u, re.I) for u in fonts), fonts
    for url in fonts:
        assert (site / "stylesheets" / url).resolve().is_file(), url


def test_the_readme_is_short_and_names_no_tracker_issue():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    pages = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
    hits = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in pages
            for m in re.finditer(r"\b[Ii]ssues? \d+\b", p.read_text())]
    assert not hits, hits


def _visible_text(html: str) -> str:
    """A page's text as a reader sees it, without code blocks, scripts and styles, line breaks kept."""
    body = re.sub(r"<pre\b.*?</pre>", "", html, flags=re.S)
    body = re.sub(r"<(script|style)\b.*?</\1>", "", body, flags=re.S)
    return re.sub(r"<[^>]+>", "", body)


def test_no_page_shows_raw_markdown_or_an_unfilled_docstring(site):
    """What Markdown or mkdocstrings failed to render shows as text: a list item indented too little
    for Python-Markdown, or with no blank line before its list, stays a text line starting with
    ``* ``; a docstring filled in at run time shows its ``{placeholder}``; TeX the math hook missed
    keeps its dollar signs and backslashes."""
    raw_bullets, placeholders, tex = [], [], []
    for f in sorted(site.rglob("*.html")):
        if f.parts[-2] == "search":
            continue
        html = f.read_text()
        text = _visible_text(html)
        name = str(f.relative_to(site))
        raw_bullets += [f"{name}: {m.group(0).strip()[:80]!r}" for m in re.finditer(r"(?:^|\n)[ \t]*\* \S[^\n]*", text)]
        tex += [f"{name}: {m.group(0)[:80]!r}" for m in re.finditer(r"\$[^$\s][^$\n]*\\[a-zA-Z]+[^$\n]*\$", text)]
        placeholders += [f"{name}: {m.group(0)}" for m in re.finditer(r"\{[a-z_]+_(?:table|rows)\}", html)]
    assert not raw_bullets, raw_bullets
    assert not placeholders, placeholders
    assert not tex, tex

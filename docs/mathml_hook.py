"""A MkDocs hook: the site's TeX math becomes MathML when the site is built, so no script renders it.

Pages write math as TeX, ``$...$`` inline and ``$$...$$`` on lines of their own (pymdownx.arithmatex
finds it, leaving code spans and code blocks alone, and wraps it as ``\\(...\\)`` / ``\\[...\\]`` in
``arithmatex`` elements). This hook replaces each wrapped formula by the MathML that latex2mathml
makes of it. Browsers draw MathML themselves (Chromium since version 109, Firefox, Safari), so the
pages need no MathJax or KaTeX, no font and nothing from another host, and the math shows with
JavaScript off. A formula latex2mathml cannot read is a build warning (an error with --strict).

mkdocs.yml enables it with ``hooks: [docs/mathml_hook.py]``; ``import blf_gym`` does not import it.
"""

from __future__ import annotations

import html
import logging
import re

from latex2mathml.converter import convert

log = logging.getLogger("mkdocs.hooks.mathml")

# pymdownx.arithmatex's output with generic: true and its default wraps.
INLINE_RE = re.compile(r'<span class="arithmatex">\\\((?P<tex>.*?)\\\)</span>', re.DOTALL)
BLOCK_RE = re.compile(r'<div class="arithmatex">\\\[(?P<tex>.*?)\\\]</div>', re.DOTALL)
# latex2mathml leaves aligned's "&" as a stray identifier; align* is the same layout and it reads it.
ALIGNED_RE = re.compile(r"\\(begin|end)\{aligned\}")
# TeX sets a thin space around a function name such as \log or \tanh (none before an opening
# parenthesis); latex2mathml writes the name as a plain <mi>, which browsers space as a letter.
FUNCTION_RE = re.compile(
    r"(?P<before></mi>|</mn>|</msub>|</msup>|</msubsup>|</mover>|</mfrac>|&#x00029;</mo>)?"
    r"(?P<name><mi>(?:sin|cos|tan|sinh|cosh|tanh|log|ln|exp|det|max|min|sup|inf|arg|sgn)</mi>)"
    r"(?P<paren>(?=<mo[^>]*>&#x00028;))?")
# A minus or plus right after a relation, an opening bracket or a comma is a sign (TeX spaces it
# tightly); browsers take any operator that is not first in its row for a binary one.
SIGN_RE = re.compile(
    r"(?P<before><mo[^>]*>&#x(?:0003D|0003C|0003E|02264|02265|02248|02192|00028|0005B|0007B|0002C);</mo>)"
    r"<mo>(?P<sign>&#x02212;|&#x0002B;)</mo>")
THIN = '<mspace width="0.1667em"></mspace>'
XMLNS = ' xmlns="http://www.w3.org/1998/Math/MathML"'  # a name, not a download; HTML does not need it


def to_mathml(tex: str, display: str, where: str) -> str:
    """The MathML for one formula (the TeX in a code element, and a warning, if it cannot be read)."""
    source = html.unescape(tex).strip()
    try:
        mathml = convert(ALIGNED_RE.sub(r"\\\1{align*}", source), display=display)
        if "<mi>&</mi>" in mathml:
            raise ValueError("an alignment mark & outside an environment that aligns")
    except Exception as exc:  # noqa: BLE001 - latex2mathml raises several kinds; any one is a bad formula
        log.warning("%s: the formula %r is not TeX that latex2mathml reads (%s)", where, source, exc)
        return f"<code>{html.escape(source)}</code>"
    mathml = mathml.replace(XMLNS, "", 1)
    mathml = SIGN_RE.sub(r'\g<before><mo form="prefix">\g<sign></mo>', mathml)
    mathml = FUNCTION_RE.sub(
        lambda m: f'{m["before"] + THIN if m["before"] else ""}{m["name"]}{"" if m["paren"] is not None else THIN}',
        mathml)
    # the TeX, for screen readers' alternatives and for copying
    return mathml.replace("<math", f'<math alttext="{html.escape(source)}"', 1)


def on_page_content(html_text: str, page, **kwargs) -> str:  # noqa: ARG001 - MkDocs passes config, files
    if "arithmatex" not in html_text:
        return html_text
    where = page.file.src_uri
    html_text = BLOCK_RE.sub(
        lambda m: f'<div class="math-block">{to_mathml(m["tex"], "block", where)}</div>', html_text)
    return INLINE_RE.sub(lambda m: to_mathml(m["tex"], "inline", where), html_text)

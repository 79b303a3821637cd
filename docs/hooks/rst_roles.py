"""mkdocs hook: Sphinx cross-reference roles in docstrings read as plain code on the site.

The docstrings name objects the Sphinx way (``:class:`~riskflow_env.config.EnvConfig```),
which Markdown renders as the role's name followed by code. This hook drops the role and,
for the ``~`` form, the path before the last name, as Sphinx shows them:
``:class:`~a.b.Name``` -> ``Name``, ``:mod:`a.b``` -> ``a.b``.
"""

from __future__ import annotations

import re

ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj|const):<code>(~?)([^<]*)</code>")


def _plain(match: re.Match[str]) -> str:
    short, target = match.groups()
    return f"<code>{target.rsplit('.', 1)[-1] if short else target}</code>"


def on_page_content(html: str, page, config, files) -> str:
    return ROLE.sub(_plain, html)

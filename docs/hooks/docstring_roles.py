"""mkdocs hook: show Sphinx roles in docstrings (``:func:`x```) as plain code.

The library's docstrings cite other functions the Sphinx way; mkdocstrings renders Markdown,
where the role would be printed literally before the code span.
"""

import re

_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|obj|exc):(?=<code>)")


def on_page_content(html, **kwargs):
    return _ROLE.sub("", html)

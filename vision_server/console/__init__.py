"""The web console's static files: one page, one style sheet and plain JavaScript modules.

No build step: the files in ``static/`` are served as they are (docs/console.md, "API", says at
which paths). The HTTP front-end that serves them and answers ``/api/*`` lives elsewhere; this
package only says where the files are.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["static_dir"]


def static_dir() -> Path:
    """The directory holding ``index.html``, ``console.css``, ``console.js`` and ``js/``."""
    return Path(__file__).resolve().parent / "static"

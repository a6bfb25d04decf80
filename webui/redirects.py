"""Where a login may send the browser next: a path on this screen, never another site.

Browsers drop tabs and newlines from a URL and read a backslash as a slash, so
``/\\evil.example`` and ``/%09/evil.example`` (a tab once decoded) lead off-site although
they start with a single slash. A target is kept only if it has no control
character or backslash at all, starts with one slash, and has neither scheme
nor host once parsed.
"""

from __future__ import annotations

from urllib.parse import urlsplit


def local_path(target: str | None) -> str | None:
    """``target`` if it is a path on this site, else None.

    >>> local_path("/history?hours=8"), local_path("//evil.example"), local_path("/\\t/evil.example")
    ('/history?hours=8', None, None)
    """
    if not target or not target.startswith("/") or target.startswith("//"):
        return None
    if "\\" in target or any(ord(c) < 0x20 or 0x7f <= ord(c) <= 0x9f for c in target):
        return None
    parts = urlsplit(target)
    if parts.scheme or parts.netloc:
        return None
    return target

"""Response headers that tell the browser what the screen's pages may do.

Every page loads its scripts and styles as files from the screen itself (no
inline script, style or event handler), so the Content-Security-Policy can
allow 'self' alone: an injected ``<script>`` or ``onload=`` would not run. No
other site may frame the screen (clickjacking an Acknowledge button), the
browser must not guess content types (an uploaded file served as a download
cannot turn into a page), and no other site learns the screen's URLs from the
Referer header.
"""

from __future__ import annotations

CONTENT_SECURITY_POLICY = "; ".join((
    "default-src 'self'",
    "script-src 'self'",
    "style-src 'self'",
    "img-src 'self'",
    "connect-src 'self'",
    "object-src 'none'",
    "base-uri 'none'",
    "form-action 'self'",
    "frame-ancestors 'none'",
))
SECURITY_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
}


def add_security_headers(response):
    """``after_request``: the headers above on every response, without overriding a view's own."""
    for name, value in SECURITY_HEADERS.items():
        response.headers.setdefault(name, value)
    return response

"""HTTP requests that never follow a redirect: the one opener illm's clients (the openai backend's
engine client, a trainer's `illm serve` client) send through, so a token or API key goes to the
configured address only. A 3xx answer is an `urllib.error.HTTPError` the caller refuses in its words."""

from __future__ import annotations

import urllib.request


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, req, fp, code, msg, headers, newurl):
        return None


NO_REDIRECTS = urllib.request.build_opener(_NoRedirect())
"""`NO_REDIRECTS.open(request, timeout=...)`: urllib's `urlopen` without following redirects."""

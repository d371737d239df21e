"""Fake HTTP peers on 127.0.0.1, each served from a thread of the test: `QuietHandler` and
`http_fake` (an engine's or a server's answers, written by the test) and `fake_hub` (a Hugging Face
hub serving local folders). Used by test_serve_hardening.py, test_trust_openai.py and test_hub.py."""

from __future__ import annotations

import asyncio
import hashlib
import http.server
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class QuietHandler(http.server.BaseHTTPRequestHandler):
    """A fake HTTP peer's handler (an engine, an `illm serve`): `reply` sends a body with its length
    and headers; nothing is logged."""

    def reply(self, status: int, body: bytes, headers: dict | None = None) -> None:
        self.send_response(status)
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@contextmanager
def http_fake(handler: type[http.server.BaseHTTPRequestHandler]) -> Iterator[str]:
    """`handler` served on 127.0.0.1 from a thread; yields its base URL, shut down after."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, args=(0.02,), daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()


@contextmanager
def fake_hub(repos: dict[str, Path], *, refuse: dict[str, tuple[int, str]] | None = None) -> Iterator[str]:
    """A Hugging Face hub on 127.0.0.1 serving each `repos[repo_id]` folder as that repository's main
    revision (the API routes `snapshot_download` calls: revision info, tree listing, file HEAD and
    GET), or answering a repository in `refuse` with (status, X-Error-Code) as the hub does for gated
    (403, GatedRepo) and missing (404, RepoNotFound) ones. Yields its URL, for HF_ENDPOINT; requests
    it served are counted in `fake_hub.requests`."""
    from aiohttp import web

    refuse = refuse or {}
    commits = {repo: hashlib.sha1(repo.encode()).hexdigest() for repo in repos}

    def files(repo):
        root = Path(repos[repo])
        return {p.name: p.read_bytes() for p in sorted(root.iterdir()) if p.is_file()}

    def refused(repo):
        status, code = refuse[repo]
        return web.Response(status=status, headers={"X-Error-Code": code, "X-Error-Message": f"{code} (fake hub)"})

    async def info(request):
        repo = f"{request.match_info['org']}/{request.match_info['name']}"
        fake_hub.requests += 1
        if repo in refuse:
            return refused(repo)
        if repo not in repos:
            return web.Response(status=404, headers={"X-Error-Code": "RepoNotFound"})
        return web.json_response({"id": repo, "sha": commits[repo],
                                  "siblings": [{"rfilename": n} for n in files(repo)]})

    async def tree(request):
        repo = f"{request.match_info['org']}/{request.match_info['name']}"
        fake_hub.requests += 1
        if repo in refuse:
            return refused(repo)
        return web.json_response([{"type": "file", "path": n, "size": len(b), "oid": hashlib.sha1(b).hexdigest()}
                                  for n, b in files(repo).items()])

    async def resolve(request):
        repo = f"{request.match_info['org']}/{request.match_info['name']}"
        fake_hub.requests += 1
        if repo in refuse:
            return refused(repo)
        body = files(repo).get(request.match_info["file"])
        if body is None:
            return web.Response(status=404, headers={"X-Error-Code": "EntryNotFound"})
        headers = {"X-Repo-Commit": commits[repo], "ETag": f'"{hashlib.sha1(body).hexdigest()}"',
                   "Content-Length": str(len(body))}
        if request.method == "HEAD":
            return web.Response(headers=headers)
        return web.Response(body=body, headers=headers)

    app = web.Application()
    app.router.add_get("/api/models/{org}/{name}/revision/{rev}", info)
    app.router.add_get("/api/models/{org}/{name}/tree/{rev:.*}", tree)
    app.router.add_route("*", "/{org}/{name}/resolve/{rev}/{file}", resolve)
    loop = asyncio.new_event_loop()
    runner = web.AppRunner(app)
    loop.run_until_complete(runner.setup())
    site = web.TCPSite(runner, "127.0.0.1", 0)
    loop.run_until_complete(site.start())
    port = site._server.sockets[0].getsockname()[1]
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    fake_hub.requests = 0
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.run_until_complete(runner.cleanup())
        loop.close()

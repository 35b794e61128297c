"""``ffrecon view`` answers only its own page: real HTTP and WebSocket requests against a running viewer.

A page on another site (cross-origin WebSocket), a DNS-rebinding page (another name in ``Host``) and any
client without the printed URL's token get 403; the viewer's own page, opened from that URL, gets the
scene. The browser end to end (Chromium opens the printed URL) is tests/test_view.py.
"""

from __future__ import annotations

import http.client
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest
from PIL import Image
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from ffrecon.geometry.alignment import Sim3
from ffrecon.view import Estimate, start_viewer
from ffrecon.view.scene import CameraLayer, CameraSpec, ImageInfo, PointLayer, ViewScene


def _tiny_scene(out: Path) -> ViewScene:
    """Two final cameras (one with a JPEG), 50 points: what a page must not be able to read."""
    (out / "images").mkdir(parents=True)
    photo = out / "images" / "a.jpg"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(photo)
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    cams = tuple(
        CameraSpec(name, np.hstack([np.eye(3), [[x], [0.0], [0.0]]]), False, K, (32, 24))
        for name, x in (("a.jpg", 0.0), ("b.jpg", 1.0))
    )
    xyz = np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32) + [0, 0, 4]
    return ViewScene(
        out_dir=out,
        layers=(CameraLayer(Estimate.FINAL, cams, Sim3.identity(), 0.0),),
        points=PointLayer(xyz, np.full((50, 3), 200, np.uint8), 50),
        splat=None,
        images={"a.jpg": ImageInfo("a.jpg", photo), "b.jpg": ImageInfo("b.jpg", None)},
        missing=(),
    )


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    viewer = start_viewer(_tiny_scene(tmp_path_factory.mktemp("view") / "out"), port=0)
    yield viewer
    viewer.stop()


def _parts(viewer) -> tuple[int, str]:
    url = urlsplit(viewer.url)
    return url.port, parse_qs(url.query)["token"][0]


def _get(port: int, path: str, headers: dict) -> tuple[int, dict, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path, headers=headers)
        response = conn.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        conn.close()


def _ws(port: int, *, path: str = "/", origin: str | None = None, headers: dict | None = None):
    import viser

    return connect(
        f"ws://127.0.0.1:{port}{path}",
        origin=origin,
        additional_headers=headers or {},
        subprotocols=[f"viser-v{viser.__version__}"],
        open_timeout=10,
        max_size=None,
    )


def _refused(port: int, **kwargs) -> int:
    """The status of a refused WebSocket handshake (fails the test when the handshake succeeds)."""
    try:
        with _ws(port, **kwargs):
            pass
    except InvalidStatus as err:
        return err.response.status_code
    pytest.fail(f"the WebSocket handshake succeeded: {kwargs}")


def test_printed_url_carries_an_unguessable_token(viewer, tmp_path):
    port, token = _parts(viewer)
    assert viewer.url == f"http://127.0.0.1:{port}/?token={token}" and len(token) >= 32
    other = start_viewer(_tiny_scene(tmp_path / "out"), port=0)
    try:
        assert _parts(other)[1] != token
    finally:
        other.stop()


def test_the_page_needs_the_token_and_then_sets_a_cookie(viewer):
    port, token = _parts(viewer)
    own = {"Host": f"127.0.0.1:{port}"}
    assert _get(port, "/", own)[0] == 403
    assert _get(port, "/?token=" + "x" * len(token), own)[0] == 403
    status, headers, body = _get(port, f"/?token={token}", own)
    assert status == 200 and b"<html" in body
    cookie = headers["Set-Cookie"]
    assert cookie.startswith(f"ffrecon-view-{port}={token};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    assert _get(port, "/", {**own, "Cookie": cookie.split(";")[0]})[0] == 200  # the page's own follow-ups
    assert _get(port, "/", {**own, "Cookie": f"ffrecon-view-{port}=wrong"})[0] == 403


def test_another_name_in_host_is_refused_even_with_the_token(viewer):
    """DNS rebinding: the attacker's name resolves to 127.0.0.1, so the browser sends its Host."""
    port, token = _parts(viewer)
    for host in (f"evil.example:{port}", f"127.0.0.1:{port + 1}", f"user@127.0.0.1:{port}", ""):
        assert _get(port, f"/?token={token}", {"Host": host})[0] == 403, host
    assert _get(port, f"/?token={token}", {"Host": f"localhost:{port}"})[0] == 200
    cookie = {"Cookie": f"ffrecon-view-{port}={token}"}
    assert _refused(port, headers={**cookie, "Host": f"evil.example:{port}"}) == 403


def test_cross_origin_websocket_is_refused_even_with_the_cookie(viewer):
    """A page on another site (or another local port) opening the viewer's WebSocket from the user's browser."""
    port, token = _parts(viewer)
    cookie = {"Cookie": f"ffrecon-view-{port}={token}"}
    for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", "null", f"https://127.0.0.1:{port}"):
        assert _refused(port, origin=origin, headers=cookie) == 403, origin
    assert _get(port, f"/?token={token}", {"Host": f"127.0.0.1:{port}", "Origin": "http://evil.example"})[0] == 403


def test_websocket_without_the_token_is_refused(viewer):
    port, _ = _parts(viewer)
    assert _refused(port, origin=f"http://127.0.0.1:{port}") == 403
    assert _refused(port, origin=f"http://127.0.0.1:{port}", headers={"Cookie": f"ffrecon-view-{port}=x"}) == 403


@pytest.mark.parametrize("how", ["page cookie", "no origin, token in the URL"])
def test_own_page_with_the_token_gets_the_scene(viewer, how):
    port, token = _parts(viewer)
    if how == "page cookie":  # what the browser does: the page's URL without the query, its cookie
        kwargs = {"origin": f"http://127.0.0.1:{port}", "headers": {"Cookie": f"ffrecon-view-{port}={token}"}}
    else:  # a non-browser client
        kwargs = {"path": f"/?token={token}"}
    with _ws(port, **kwargs) as ws:
        first = ws.recv(timeout=10)  # viser sends the whole scene in one frame
    assert isinstance(first, bytes)
    import zstandard  # viser's dependency: it compresses its frames

    payload = zstandard.ZstdDecompressor().decompressobj().decompress(first[first.index(b"\x28\xb5\x2f\xfd") :])
    assert b"\xff\xd8\xff" in payload  # the photo on the frustum, as JPEG


def test_wildcard_host_still_checks_the_name_and_needs_the_token():
    """``--host 0.0.0.0``: reached under any of this machine's addresses, never under another name."""
    from websockets.datastructures import Headers
    from websockets.http11 import Request

    from ffrecon.view.access import AccessPolicy

    policy = AccessPolicy(host="0.0.0.0", port=8080, token="t" * 43)
    lan = Headers({"Host": "192.168.1.7:8080"})
    assert policy.refusal(Request("/", lan)) == "no token, or a wrong one"
    assert policy.refusal(Request("/?token=" + "t" * 43, lan)) == ""
    assert all(policy.own_host(h) for h in ("192.168.1.7:8080", "[fe80::1]:8080", "localhost:8080", "0.0.0.0:8080"))
    assert not any(policy.own_host(h) for h in ("evil.example:8080", "192.168.1.7:8081", "192.168.1.7"))
    assert policy.own_origin("http://192.168.1.7:8080") and not policy.own_origin("http://evil.example:8080")
    named = AccessPolicy(host="viewer.lan", port=9000, token="t" * 43)
    assert named.own_host("viewer.lan:9000") and named.own_host("127.0.0.1:9000")
    assert not named.own_host("192.168.1.7:9000") and not named.own_host("other.lan:9000")
    assert not AccessPolicy(host="127.0.0.1", port=8080, token="t" * 43).own_host("192.168.1.7:8080")


def test_a_viser_that_bypasses_the_guard_is_not_served(tmp_path, monkeypatch):
    """A viser version that starts its server without ``websockets.asyncio.server.serve``: refused, not open."""
    import contextlib

    from ffrecon.errors import ResourceError
    from ffrecon.view import server

    monkeypatch.setattr(server, "guarded_serve", lambda gate: contextlib.nullcontext(gate))
    with pytest.raises(ResourceError, match="cannot guard") as err:
        start_viewer(_tiny_scene(tmp_path / "out"), port=0)
    assert "pip install" in err.value.fix

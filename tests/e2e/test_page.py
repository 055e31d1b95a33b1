"""The live map page in headless Chromium against a real `uavmm demo` (fusion server + three agents):
it shows the three UAVs, the heatmap and the global tracks; the cursor readout, wheel zoom, drag pan
and the scale bar work; a screenshot is a PNG with the map drawn on it.

Chromium is driven over the DevTools protocol with a minimal stdlib websocket client (no new
dependency). Skipped, with the reason printed, where Debian's chromium is not installed
(`.ci/run` installs it).
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.e2e.conftest import ENV, REPO, uavmm
from tests.netutil import free_port, wait_until

pytestmark = pytest.mark.e2e
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars", "--window-size=1400,900"]
#: Background of the map area (#map in map.css): pixels of another colour were drawn.
MAP_BACKGROUND_RGB = (0xE8, 0xEB, 0xE4)


def chromium_path() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


class DevTools:
    """A DevTools-protocol client over a websocket (RFC 6455 client side: masked text frames)."""

    def __init__(self, ws_url: str, timeout_s: float = 30.0) -> None:
        url = urllib.parse.urlparse(ws_url)
        self.sock = socket.create_connection((url.hostname, url.port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            f"GET {url.path} HTTP/1.1\r\nHost: {url.hostname}:{url.port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
        self.reader = self.sock.makefile("rb")
        status = self.reader.readline()
        assert b" 101 " in status, f"websocket handshake refused: {status!r}"
        while self.reader.readline() not in (b"\r\n", b""):
            pass
        self.next_id = 0

    def _send(self, text: str) -> None:
        payload = text.encode()
        header = bytearray([0x81])
        n = len(payload)
        if n < 126:
            header.append(0x80 | n)
        elif n < 1 << 16:
            header += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            header += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(bytes(header) + mask + masked)

    def _read_exact(self, n: int) -> bytes:
        data = self.reader.read(n)
        if data is None or len(data) != n:
            raise ConnectionError("devtools websocket closed")
        return data

    def _recv(self) -> str:
        parts = []
        while True:
            b0, b1 = self._read_exact(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read_exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read_exact(8))[0]
            payload = self._read_exact(n)  # server frames are not masked
            opcode = b0 & 0x0F
            if opcode == 8:
                raise ConnectionError("devtools websocket closed by the browser")
            if opcode in (0, 1, 2):
                parts.append(payload)
                if b0 & 0x80:
                    return b"".join(parts).decode()

    def call(self, method: str, **params) -> dict:
        """Send one command and return its result (events in between are skipped)."""
        self.next_id += 1
        self._send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            message = json.loads(self._recv())
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def evaluate(self, expression: str):
        """The JSON value of a JavaScript expression in the page."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def mouse(self, kind: str, x: float, y: float, **extra) -> None:
        self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, **extra)

    def close(self) -> None:
        self.sock.close()


def start_demo(tmp: Path) -> tuple[subprocess.Popen, str]:
    """`uavmm demo` on free ports; returns the process and the map URL once the agents are up."""
    log_path = tmp / "demo.out"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(
            uavmm("demo", "--http", "127.0.0.1:0", "--duration", "300", "--status-every", "0", "--log-dir",
                  str(tmp / "logs")),
            cwd=REPO, env=ENV, stdout=out, stderr=subprocess.STDOUT)
    def started():
        text = log_path.read_text()
        return text if "UAVs flying" in text or proc.poll() is not None else None

    text = wait_until(started, 90.0, "demo start")
    assert "UAVs flying" in text, text
    return proc, re.search(r"map: (http://\S+)", text).group(1)


def start_chromium(url: str, tmp: Path) -> tuple[subprocess.Popen, str]:
    """Headless Chromium on `url` with a DevTools port; returns the process and the page's websocket URL."""
    stderr_path = tmp / "chromium.err"
    with open(stderr_path, "wb") as err:
        proc = subprocess.Popen([chromium_path(), *CHROMIUM_FLAGS, f"--user-data-dir={tmp / 'profile'}",
                                 "--remote-debugging-port=0", url],
                                stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    match = wait_until(lambda: re.search(r"DevTools listening on ws://([^/]+)/",
                                         stderr_path.read_text(errors="replace")),
                       30.0, "chromium's DevTools endpoint")
    host = match.group(1)

    def page_target():
        with urllib.request.urlopen(f"http://{host}/json/list", timeout=5) as response:
            pages = [t for t in json.loads(response.read()) if t.get("type") == "page"]
        return pages[0]["webSocketDebuggerUrl"] if pages else None

    return proc, wait_until(page_target, 15.0, "chromium page target")


def test_page_and_its_assets_are_served_and_fetch_nothing_from_elsewhere():
    """Without a browser: `/` and `/static/map.js|css` are served by the app, and the page's files name
    no other host (offline: no CDN, no web fonts, no base map)."""
    from fusion_server.config import FusionSettings
    from fusion_server.server import FusionServer, HttpThread

    def get(path: str) -> tuple[int, str, str]:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{http.port}{path}", timeout=10) as response:
                return response.status, response.headers["content-type"], response.read().decode()
        except urllib.error.HTTPError as exc:
            return exc.code, "", ""

    server = FusionServer(FusionSettings(db_path=None, http_port=0))  # no Zenoh needed for static files
    http = HttpThread(server.app, "127.0.0.1", 0)
    http.start()
    try:
        status, _, page = get("/")
        assert status == 200 and 'src="/static/map.js"' in page and "/static/map.css" in page
        assert not re.search(r"https?://", page)
        for path, kind in (("/static/map.js", "javascript"), ("/static/basemap.js", "javascript"),
                           ("/static/details.js", "javascript"), ("/static/timeline.js", "javascript"),
                           ("/static/map.css", "text/css")):
            status, content_type, text = get(path)
            assert status == 200 and kind in content_type
            assert not re.search(r"(https?:)?//[\w.-]+\.[a-z]{2,}[/:]", text), f"{path} names a host"
        assert get("/static/nosuch.js")[0] == 404
    finally:
        http.stop()
        server.close()


def test_page_shows_three_uavs_heatmap_and_tracks(tmp_path):
    chromium = chromium_path()
    if chromium is None:
        reason = "Debian chromium is not installed (.ci/run installs it: apt-get install chromium chromium-driver)"
        print(f"SKIPPED: {reason}")
        pytest.skip(reason)
    tmp = Path(tempfile.mkdtemp(prefix="uavmm-page-", dir=tmp_path))
    demo, url = start_demo(tmp)
    browser = devtools = None
    try:
        browser, ws_url = start_chromium(url, tmp)
        devtools = DevTools(ws_url)
        # null until the page has loaded
        summary_js = "(e => e && JSON.stringify(Object.assign({}, e.dataset)))(document.getElementById('summary'))"

        def ready():
            found = devtools.evaluate(summary_js)
            if not found:
                return None
            s = json.loads(found)
            ok = s["status"] == "ok" and s["uavsOnline"] == "3" and int(s["heatTiles"]) > 0 and int(s["tracks"]) > 0
            return s if ok else None

        summary = wait_until(ready, 30.0, "three UAVs, heatmap tiles and tracks on the page")
        assert summary["cls"] == "person" and int(summary["objects"]) >= 0
        uav_items = devtools.evaluate(
            "[...document.querySelectorAll('#uav-list li')].map(li => [li.dataset.uav, li.dataset.online])")
        assert sorted(uav_items) == [["uav1", "true"], ["uav2", "true"], ["uav3", "true"]]
        assert devtools.evaluate("document.querySelectorAll('#track-list li').length") >= 1
        # the page draws what the server says: same UAVs and tracks as the REST API
        with urllib.request.urlopen(url + "v1/uavs", timeout=5) as response:
            assert sorted(u["id"] for u in json.loads(response.read())) == ["uav1", "uav2", "uav3"]

        # cursor readout: the lat/lon under the mouse, in the demo's scene (trio: 48.5335 N, 9.0555 E)
        devtools.mouse("mouseMoved", 500, 400)
        readout = wait_until(lambda: devtools.evaluate(
            "(e => e.dataset.source === 'cursor' && [e.textContent, +e.dataset.lat, +e.dataset.lon])"
            "(document.getElementById('cursor'))"), 5.0, "cursor readout")
        text, lat, lon = readout
        assert re.fullmatch(r"\d+\.\d{6}° N, \d+\.\d{6}° E", text), text
        assert abs(lat - 48.5335) < 0.01 and abs(lon - 9.0555) < 0.01

        # wheel zoom in at the cursor: zoom +0.5 and the scale bar shows fewer metres
        def zoom() -> float:
            return float(devtools.evaluate("document.getElementById('summary').dataset.zoom"))

        zoom0 = zoom()
        metres0 = float(devtools.evaluate("document.getElementById('scale').dataset.metres"))
        devtools.mouse("mouseWheel", 500, 400, deltaX=0, deltaY=-100)
        wait_until(lambda: abs(zoom() - zoom0) > 0.1, 5.0, "wheel zoom")
        zoom1 = zoom()
        assert zoom1 == pytest.approx(zoom0 + 0.5, abs=0.02)
        devtools.mouse("mouseWheel", 500, 400, deltaX=0, deltaY=-100)
        devtools.mouse("mouseWheel", 500, 400, deltaX=0, deltaY=-100)
        wait_until(lambda: float(devtools.evaluate("document.getElementById('scale').dataset.metres")) < metres0,
                 5.0, "a shorter scale bar after zooming in")
        # the point under the cursor stays put while zooming
        devtools.mouse("mouseMoved", 500, 400)
        lat2, lon2 = devtools.evaluate("(e => [+e.dataset.lat, +e.dataset.lon])(document.getElementById('cursor'))")
        assert lat2 == pytest.approx(lat, abs=2e-6) and lon2 == pytest.approx(lon, abs=2e-6)

        # drag 100 px to the right: the map moves with the mouse, so the point now under (500, 400) lies west
        devtools.mouse("mousePressed", 500, 400, button="left", clickCount=1)
        devtools.mouse("mouseMoved", 550, 400, button="left", buttons=1)
        devtools.mouse("mouseMoved", 600, 400, button="left", buttons=1)
        devtools.mouse("mouseReleased", 600, 400, button="left", clickCount=1)
        devtools.mouse("mouseMoved", 500, 400)

        def cursor_latlon() -> list[float]:
            return devtools.evaluate("(e => [+e.dataset.lat, +e.dataset.lon])(document.getElementById('cursor'))")

        wait_until(lambda: cursor_latlon()[1] < lon - 1e-6, 5.0, "pan by dragging")
        lat3, lon3 = cursor_latlon()
        assert lat3 == pytest.approx(lat, abs=2e-6)

        devtools.evaluate("document.getElementById('fit').click()")
        time.sleep(1.5)  # one more poll so the screenshot shows the fitted view with fresh data
        shot = base64.b64decode(devtools.call("Page.captureScreenshot", format="png")["data"])
        path = tmp_path / "map.png"
        path.write_bytes(shot)
        print(f"screenshot: {path}")
        assert shot[:8] == b"\x89PNG\r\n\x1a\n"
        image = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 500 and image.shape[1] > 1000
        map_area = image[90:-60, 20:1000][:, :, ::-1].astype(np.int16)  # RGB, away from the overlays
        drawn = np.abs(map_area - np.array(MAP_BACKGROUND_RGB)).sum(axis=2) > 30
        assert drawn.mean() > 0.03, f"only {drawn.mean():.1%} of the map area differs from the background"
        warm = (map_area[:, :, 0] > 180) & (map_area[:, :, 2] < 120)  # inferno's orange/yellow: the heatmap
        assert warm.sum() > 50
    finally:
        if devtools is not None:
            devtools.close()
        if browser is not None:
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=10)
        demo.send_signal(signal.SIGINT)
        try:
            code = demo.wait(timeout=40)
        except subprocess.TimeoutExpired:
            demo.kill()
            raise
    assert code == 0, (tmp / "demo.out").read_text()


def test_page_with_a_rest_token_shows_the_map_and_without_it_says_why(tmp_path, server_factory_secured):
    """A server with REST tokens: the page opened as .../#token=TOKEN loads data and heatmap tiles, takes the
    token out of the address bar and keeps it on reload; opened without it, it says it needs a token."""
    chromium = chromium_path()
    if chromium is None:
        reason = "Debian chromium is not installed (.ci/run installs it: apt-get install chromium chromium-driver)"
        print(f"SKIPPED: {reason}")
        pytest.skip(reason)
    url, token = server_factory_secured
    summary_js = "(e => e && JSON.stringify(Object.assign({}, e.dataset)))(document.getElementById('summary'))"
    for with_token in (True, False):
        tmp = Path(tempfile.mkdtemp(prefix="uavmm-page-", dir=tmp_path))
        browser, ws_url = start_chromium(url + (f"#token={token}" if with_token else ""), tmp)
        devtools = DevTools(ws_url)
        try:
            def status(wanted: str, devtools: DevTools = devtools):
                found = devtools.evaluate(summary_js)
                s = json.loads(found) if found else None
                return s if s and s["status"] == wanted else None

            if with_token:
                summary = wait_until(lambda: (s := status("ok")) and int(s["heatTiles"]) > 0 and s, 30.0,
                                   "data and heatmap tiles with the token")
                assert summary["uavsOnline"] == "1"
                assert devtools.evaluate("window.location.hash") == ""  # out of the address bar
                devtools.call("Page.reload")
                wait_until(lambda: status("ok"), 30.0, "data after a reload (token kept for the tab)")
            else:
                wait_until(lambda: status("error"), 30.0, "an error status without the token")
                assert "needs a token" in devtools.evaluate("document.getElementById('status').textContent")
        finally:
            devtools.close()
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=10)


@pytest.fixture
def server_factory_secured():
    """A fusion server with one REST token and one fake UAV publishing a tile; yields (page URL, token)."""
    from fusion_server.config import FusionSettings, ZenohOptions
    from fusion_server.http_auth import HttpToken
    from fusion_server.server import FusionServer
    from tests.fusion_server.fake_agent import FakeAgent, blob

    token = "page-token-0123456789abcdef"
    port = free_port()
    options = ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    server = FusionServer(FusionSettings(zenoh=options, http_port=0, db_path=None, ttl_s=30.0,
                                         http_tokens=(HttpToken("page", token),)))
    server.start()
    agent = FakeAgent("uav1", f"tcp/127.0.0.1:{port}")
    try:
        agent.state()
        agent.tile(blob(128, 128, value=0.9, sigma=8.0))
        wait_until(lambda: server.joint.tiles(), 10.0, "the fake UAV's tile in the joint map")
        yield server.url, token
    finally:
        agent.close()
        server.close()


def test_api_docs_render_offline_in_chromium(tmp_path, server_factory_secured):
    """/docs (Swagger UI) and /redoc render the API from local assets: Chromium here has no internet."""
    if chromium_path() is None:
        reason = "Debian chromium is not installed (.ci/run installs it: apt-get install chromium chromium-driver)"
        print(f"SKIPPED: {reason}")
        pytest.skip(reason)
    url, _token = server_factory_secured
    for path, count_js in (("docs", "document.querySelectorAll('.swagger-ui .opblock').length"),
                           ("redoc", "document.querySelectorAll('[data-section-id^=\"operation\"]').length")):
        tmp = Path(tempfile.mkdtemp(prefix="uavmm-docs-", dir=tmp_path))
        browser, ws_url = start_chromium(url + path, tmp)
        devtools = DevTools(ws_url)
        try:
            operations = wait_until(lambda js=count_js, d=devtools: d.evaluate(js), 30.0, f"operations on /{path}")
            assert operations >= 8  # healthz, uavs, map, tiles, tilejson, objects, tracks, joint tiles, metrics
        finally:
            devtools.close()
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=10)


def test_page_draws_an_offline_basemap_a_marker_legend_and_declutters_labels(tmp_path):
    """An MBTiles basemap served by the server itself under the map, its attribution, the marker legend,
    and twelve tracks on one spot: their markers are drawn, overlapping labels are left out."""
    if chromium_path() is None:
        reason = "Debian chromium is not installed (.ci/run installs it: apt-get install chromium chromium-driver)"
        print(f"SKIPPED: {reason}")
        pytest.skip(reason)
    from fusion_server.config import FusionSettings, ZenohOptions
    from fusion_server.server import FusionServer
    from tests.fusion_server.fake_agent import LAT, LON, FakeAgent, blob
    from tests.fusion_server.test_basemap import ROW_COLOURS, make_mbtiles
    from tests.netutil import free_port, wait_until

    mbtiles = make_mbtiles(tmp_path / "ortho.mbtiles")
    port = free_port()
    options = ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    server = FusionServer(FusionSettings(zenoh=options, http_port=0, db_path=None, ttl_s=30.0, track_hold_s=60.0,
                                         basemap=str(mbtiles)))
    server.start()
    agent = FakeAgent("uav1", f"tcp/127.0.0.1:{port}")
    browser = devtools = None
    try:
        agent.state()
        agent.tile(blob(128, 128, value=0.9, sigma=8.0))
        agent.tracks([(i, "person", LAT + i * 2e-7, LON) for i in range(12)])
        wait_until(lambda: len(server.tracker) == 12, 10.0)
        browser, ws_url = start_chromium(server.url, tmp_path)
        devtools = DevTools(ws_url)
        summary_js = "(e => e && JSON.stringify(Object.assign({}, e.dataset)))(document.getElementById('summary'))"

        def ready():
            found = devtools.evaluate(summary_js)
            s = json.loads(found) if found else None
            return s if s and s["status"] == "ok" and int(s["basemapTiles"]) > 0 and s["tracks"] == "12" else None

        summary = wait_until(ready, 30.0, "basemap tiles and twelve tracks on the page")
        assert int(summary["hiddenLabels"]) >= 8  # twelve labels on one spot: most are left out
        assert devtools.evaluate("document.getElementById('attribution').textContent") == "test orthophoto"
        assert devtools.evaluate("document.getElementById('markers').offsetHeight") > 50
        # click for details on the spot of the UAV and its tracks; a click on empty map closes the panel
        rect = devtools.evaluate("(r => [r.left, r.top])(document.getElementById('map').getBoundingClientRect())")
        x, y = devtools.evaluate(f"window.uavmmMap.toScreen({LAT}, {LON})")
        for kind in ("mousePressed", "mouseReleased"):
            devtools.mouse(kind, rect[0] + x, rect[1] + y, button="left", clickCount=1)
        details = wait_until(lambda: devtools.evaluate(
            "(e => !e.hidden && [e.dataset.kind, e.textContent])(document.getElementById('details'))"), 5.0,
            "the details panel")
        assert details[0] in ("uav", "track") and "status" in details[1] and "position" in details[1]
        for kind in ("mousePressed", "mouseReleased"):
            devtools.mouse(kind, rect[0] + 30, rect[1] + 400, button="left", clickCount=1)
        wait_until(lambda: devtools.evaluate("document.getElementById('details').hidden"), 5.0, "the panel closed")
        shot = devtools.call("Page.captureScreenshot", format="png")
        image = cv2.imdecode(np.frombuffer(base64.b64decode(shot["data"]), np.uint8), cv2.IMREAD_COLOR)
        (tmp_path / "basemap.png").write_bytes(base64.b64decode(shot["data"]))
        colours = {tuple(int(v) for v in c) for c in ROW_COLOURS}
        pixels = image.reshape(-1, 3)
        hits = sum(int(np.all(pixels == np.array(c, np.uint8), axis=1).sum()) for c in colours)
        assert hits > 0.2 * len(pixels), f"only {hits / len(pixels):.0%} of the screenshot shows the basemap"
    finally:
        if devtools is not None:
            devtools.close()
        if browser is not None:
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=10)
        agent.close()
        server.close()


def test_page_time_slider_replays_the_tracks_from_the_history(tmp_path):
    """Drag the time slider back: the track is drawn where it was then (west of where it is now, the
    person walks east); the live button brings the live tracks back."""
    if chromium_path() is None:
        reason = "Debian chromium is not installed (.ci/run installs it: apt-get install chromium chromium-driver)"
        print(f"SKIPPED: {reason}")
        pytest.skip(reason)
    from fusion_server.config import FusionSettings, ZenohOptions
    from fusion_server.server import FusionServer
    from tests.fusion_server.fake_agent import LAT, LON, FakeAgent
    from tests.netutil import free_port, wait_until

    port = free_port()
    options = ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    server = FusionServer(FusionSettings(zenoh=options, http_port=0, db_path=tmp_path / "f.sqlite", ttl_s=30.0,
                                         track_hold_s=60.0, track_history_interval_s=0.2, persist_interval_s=0.2))
    server.start()
    agent = FakeAgent("uav1", f"tcp/127.0.0.1:{port}")
    browser = devtools = None
    try:
        agent.state()
        for k in range(15):  # 3 s walking east
            agent.tracks([(1, "person", LAT, LON + k * 2e-5)])
            time.sleep(0.2)
        browser, ws_url = start_chromium(server.url, tmp_path)
        devtools = DevTools(ws_url)
        slider_ready = "(s => s && !s.disabled && +s.max - +s.min >= 2)(document.getElementById('time-slider'))"
        wait_until(lambda: devtools.evaluate(slider_ready), 30.0, "the time slider with a history range")
        # the live tracks come with the page's own polling, which need not be done when the slider is
        wait_until(lambda: devtools.evaluate("window.uavmmMap.state.liveTracks.length"), 30.0, "the live tracks")
        live_lon = devtools.evaluate("window.uavmmMap.state.liveTracks[0].geometry.coordinates[0]")
        devtools.evaluate("(s => { s.value = String(+s.min + 1); s.dispatchEvent(new Event('input')); })"
                          "(document.getElementById('time-slider'))")
        summary_js = "(e => JSON.stringify(Object.assign({}, e.dataset)))(document.getElementById('summary'))"
        replay = wait_until(lambda: (lambda s: s if s["replay"] else None)(json.loads(devtools.evaluate(summary_js))),
                            10.0, "the page in replay")
        assert replay["tracks"] == "1"
        replay_lon = devtools.evaluate("window.uavmmMap.state.tracks[0].geometry.coordinates[0]")
        assert LON - 1e-9 <= replay_lon < live_lon - 1e-5
        assert "replay" in devtools.evaluate("document.getElementById('time-label').textContent")
        devtools.evaluate("document.getElementById('time-live').click()")
        wait_until(lambda: json.loads(devtools.evaluate(summary_js))["replay"] == "", 10.0, "the page live again")
        assert devtools.evaluate("document.getElementById('time-label').textContent") == "live"
    finally:
        if devtools is not None:
            devtools.close()
        if browser is not None:
            os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=10)
        agent.close()
        server.close()

"""The browser viewer: viser's scene arrays and camera against slow references, the offline page, and a
slow test that opens the page in headless Chromium and compares its screenshot with our renderer.

The browser test needs Debian's `chromium` package (`apt-get install -y chromium`); it is skipped,
saying so, where `chromium` is not on PATH. Nothing here uses a network: the page is served from a
local `http.server` on 127.0.0.1 and embeds its scene; Chromium is driven through its DevTools
protocol on a 127.0.0.1 websocket (screenshots until the page has settled).
"""

from __future__ import annotations

import base64
import functools
import http.server
import json
import shutil
import subprocess
import threading
import urllib.request

import numpy as np
import pytest
import torch

from mvgeo.camera import Camera
from mvgeo.sparse_model import PosedImage, SparseModel
from splat.viewer import ViewerCamera, export_html, viewer_arrays
from tests.splat.scenes import look_at_cam_from_world
from tests.splat.test_export import _model

CHROMIUM_HELP = "headless Chromium is needed: install Debian's package with `apt-get install -y chromium`"


def _R_reference(q):
    """Rotation matrix of a unit wxyz quaternion, written out."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_viewer_arrays_match_a_per_gaussian_reference():
    model = _model(40, seed=11)
    a = viewer_arrays(model)
    p = {k: v.detach().double().numpy() for k, v in model.params_dict().items()}
    for i in range(40):
        q = p["quats"][i] / np.linalg.norm(p["quats"][i])
        R = _R_reference(q)
        S = np.diag(np.exp(p["log_scales"][i]))
        np.testing.assert_allclose(a["covariances"][i], R @ S @ S @ R.T, rtol=1e-5, atol=1e-9)
        rgb = np.clip(0.5 + 0.28209479177387814 * p["sh0"][i, 0], 0, 1)
        np.testing.assert_allclose(a["rgbs"][i], rgb, atol=1e-6)
        np.testing.assert_allclose(a["opacities"][i, 0], 1 / (1 + np.exp(-p["opacity_logits"][i])), atol=1e-6)
    np.testing.assert_array_equal(a["centers"], p["means"].astype(np.float32))


@pytest.mark.parametrize("name", ["opacity_logits", "sh0", "means", "log_scales"])
def test_viewer_arrays_refuse_non_finite_parameters_naming_them(name):
    from mvgeo.common.errors import InputError

    model = _model(6, seed=3)
    with torch.no_grad():
        getattr(model, name).view(-1)[2] = float("nan")
    with pytest.raises(InputError, match=name):  # viser would cast a NaN colour or opacity to some byte
        viewer_arrays(model)


def test_viewer_camera_is_the_colmap_view():
    cfw = look_at_cam_from_world([0.3, -0.2, -3.0], [0.0, 0.1, 0.0]).numpy()
    cam = Camera.pinhole(400.0, 400.0, 160.0, 120.0, 320, 240)
    v = ViewerCamera.from_colmap(cam, cfw)
    np.testing.assert_allclose(v.position, [0.3, -0.2, -3.0], atol=1e-12)
    # the look-at point projects to the principal point, the up vector points to smaller v
    p_cam = cfw[:3, :3] @ v.look_at + cfw[:3, 3]
    np.testing.assert_allclose(p_cam[:2] / p_cam[2], [0.0, 0.0], atol=1e-12)
    up_cam = cfw[:3, :3] @ v.up
    np.testing.assert_allclose(up_cam, [0.0, -1.0, 0.0], atol=1e-12)
    assert v.fov_y_rad == pytest.approx(2 * np.arctan(120.0 / 400.0))
    assert "initialCameraFov=" in v.url_query() and "initialCameraPosition=0.3,-0.2,-3" in v.url_query()


def _sparse(cam: Camera, cfw: np.ndarray) -> SparseModel:
    return SparseModel(cameras={1: cam}, images=[PosedImage("view_a.png", 1, cfw[:3])])


def test_export_html_writes_one_self_contained_page(tmp_path):
    cfw = look_at_cam_from_world([0.3, -0.2, -3.0], [0.0, 0.0, 0.0]).numpy()
    cam = Camera.pinhole(384.0, 384.0, 160.0, 120.0, 320, 240)
    index = export_html(_model(200, seed=12), tmp_path / "view", sparse=_sparse(cam, cfw))
    assert index == (tmp_path / "view" / "index.html").resolve()
    page = index.read_text()
    assert "window.__VISER_EMBED_DATA__=" in page  # the scene is inside the page
    embedded = page.split('window.__VISER_EMBED_DATA__="', 1)[1].split('"', 1)[0]
    assert len(base64.b64decode(embedded)) > 200 * 8  # viser packs 32 bytes per Gaussian before zstd
    assert "viser" in (tmp_path / "view" / "NOTICE.txt").read_text()


def _serve(folder):
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


class _Chromium:
    """Headless Chromium driven over the DevTools protocol (websocket, 127.0.0.1 only)."""

    def __init__(self, profile, width: int, height: int):
        import re

        self.proc = subprocess.Popen(
            ["chromium", "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             f"--window-size={width},{height}", "--hide-scrollbars", "--remote-debugging-address=127.0.0.1",
             "--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        endpoint = None
        for line in self.proc.stderr:
            m = re.search(r"DevTools listening on (ws://\S+)", line)
            if m:
                endpoint = m.group(1)
                break
        if endpoint is None:
            self.proc.kill()
            raise AssertionError("chromium did not start its DevTools endpoint")
        port = endpoint.split(":")[2].split("/")[0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            page = next(t for t in json.loads(r.read()) if t["type"] == "page")
        from websockets.sync.client import connect

        self.ws = connect(page["webSocketDebuggerUrl"], max_size=None)
        self.next_id = 0
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})

    def call(self, method: str, params: dict | None = None) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params or {}}))
        while True:
            msg = json.loads(self.ws.recv(timeout=120))
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise AssertionError(f"{method}: {msg['error']}")
                return msg["result"]

    def screenshot(self) -> np.ndarray:
        from mvgeo.common.deps import cv2

        png = base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])
        bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        return np.ascontiguousarray(bgr[:, :, ::-1], dtype=np.float32) / 255.0

    def close(self) -> None:
        self.ws.close()
        self.proc.kill()
        self.proc.wait(timeout=30)


def _settled_screenshot(browser: _Chromium, url: str, timeout_s: float = 240.0) -> np.ndarray:
    """Load `url` and screenshot it once it has settled: the client fades the Gaussians in and sorts them
    in a worker, so screenshots are taken every 2 s until two in a row agree (mean difference < 0.5/255)."""
    import time

    browser.call("Page.enable")
    browser.call("Page.navigate", {"url": url})
    previous, deadline = None, time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(2.0)
        shot = browser.screenshot()
        if previous is not None and np.mean(np.abs(shot - previous)) < 0.5 / 255 and np.mean(shot) < 0.99:
            return shot
        previous = shot
    raise AssertionError(f"the viewer page did not settle within {timeout_s:.0f} s")


@pytest.mark.slow
def test_viewer_page_in_headless_chromium_matches_our_renderer(tmp_path):
    """Open `index.html` from a local http.server in headless Chromium at a known camera.

    Compared: the screenshot against our rasterizer's image of the same pinhole camera (principal point
    at the centre, as viser's viewport has; SH degree 0, the only colour viser draws; white background,
    viser's), outside the two overlays the client draws (its software-WebGL notice top left, its menu
    button top right). Measured 40.7 dB on this scene (Chromium 156, swiftshader WebGL); the same page
    with the up vector flipped scored 18.3 dB, with the field of view 10 % too wide 18.9 dB, with the
    horizontal field of view taken for the vertical one 12.5 dB. The bar, 30 dB, passes the viewer's own
    approximations (fp16 covariances, 8-bit colours, a 2.8 sigma cut-off, a 0.01 alpha test) and fails
    any of those camera errors.
    """
    if shutil.which("chromium") is None:
        pytest.skip(CHROMIUM_HELP)
    W, H = 640, 480
    model = _model(3000, seed=1)
    cfw = look_at_cam_from_world([0.3, -0.2, -3.0], [0.0, 0.0, 0.0]).numpy()
    cam = Camera.pinhole(1.2 * W, 1.2 * W, W / 2, H / 2, W, H)
    view = ViewerCamera.from_colmap(cam, cfw)
    export_html(model, tmp_path / "view", initial=view)
    with torch.no_grad():
        ref = model.render(torch.as_tensor(cfw, dtype=torch.float32), torch.as_tensor(cam.K, dtype=torch.float32),
                           W, H, sh_degree=0, background=torch.ones(3)).rgb.clamp(0, 1).permute(1, 2, 0).numpy()
    server = _serve(tmp_path / "view")
    browser = _Chromium(tmp_path / "profile", W, H)
    try:
        url = (f"http://127.0.0.1:{server.server_address[1]}/index.html?hideViserLogo&fixedDpr=1&"
               + view.url_query())
        shot = _settled_screenshot(browser, url)
    finally:
        browser.close()
        server.shutdown()
    assert shot.shape == (H, W, 3)
    keep = np.ones((H, W), bool)
    keep[:140, :300] = False  # notification "Software WebGL rendering detected"
    keep[:60, W - 60:] = False  # the client's menu button
    # non-blank: the splat covers a good part of the page (not just the white background)
    assert np.mean(np.abs(shot[keep] - 1.0).max(axis=1) > 0.1) > 0.3
    mse = float(np.mean((shot[keep] - ref[keep]) ** 2))
    psnr_db = -10 * np.log10(mse)
    print(f"viewer screenshot vs our render: {psnr_db:.2f} dB")
    assert psnr_db >= 30.0


def test_view_serves_the_client_on_localhost():
    import socket
    import time
    import urllib.request

    from splat.viewer import serve

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(_model(50, seed=13),), daemon=True,
                              kwargs={"host": "127.0.0.1", "port": port, "stop": stop})
    thread.start()
    body, deadline = None, time.monotonic() + 20.0
    while body is None and time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=1.0) as r:
                body = r.read()
        except OSError:
            time.sleep(0.2)
    stop.set()
    thread.join(timeout=10)
    assert body is not None and b"<html" in body.lower()
    assert not thread.is_alive()

"""Look at a splat in a browser: a live viser server (`splat view`) or an offline page (`splat export
--format html`, `OUT/view/` of `denoise-gs run`).

Both put the same scene into viser (https://viser.studio, Apache-2.0, a PyPI dependency): the
Gaussians (`add_gaussian_splats`: centres, covariances `R diag(s^2) R^T`, DC colour
`0.5 + SH_C0 * f_dc` clipped to [0, 1], opacity; viser renders no view-dependent colour) and,
when a COLMAP model is given, one camera frustum per view. The offline page is viser's own
prebuilt web client (shipped in the viser wheel) with the serialised scene embedded
(`StateSerializer.as_html`): one self-contained `index.html` that fetches nothing, so it opens
from disk or from any static file server with no network.

Cameras: viser's camera frames use OpenCV axes, like ours; its viewport camera takes a
position, a look-at point, an up vector and a vertical field of view (radians), with the
principal point at the image centre (`ViewerCamera.from_colmap`).
"""

from __future__ import annotations

import contextlib
import io
import socket
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mvgeo.camera import Camera
from mvgeo.common.atomic import atomic_output_dir
from mvgeo.common.errors import InputError
from mvgeo.common.output import OutputPlan, as_output_plan
from mvgeo.sparse_model import SparseModel
from mvgeo.transforms import R_from_quat, quat_from_R
from splat.export import SH_C0
from splat.gaussian_model import GaussianModel

__all__ = ["VIEW_NOTICE", "ViewerCamera", "add_scene", "export_html", "serve", "viewer_arrays", "viewer_page",
           "write_view_folder"]

#: Written next to the page: what it is and whose client it runs.
VIEW_NOTICE = """\
index.html: an offline viewer of a Gaussian-splat scene (and its cameras), written by denoise-gs.
Open it in a browser (double-click, or serve this folder: python -m http.server -d . 8000).
It needs no network: the scene is embedded in the page.

The page is the web client of viser (https://github.com/viser-project/viser), Apache License 2.0,
copied from the installed viser package with the scene injected. Drag to orbit, scroll to zoom,
right-drag to pan.
"""


@dataclass(frozen=True)
class ViewerCamera:
    """A viewport camera as viser takes it (world coordinates, vertical field of view).

    Attributes:
        position: (3,) camera centre.
        look_at: (3,) a point on the optical axis.
        up: (3,) the image's up direction (-y of the OpenCV camera) in the world.
        fov_y_rad: vertical field of view in radians.
    """

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov_y_rad: float

    @classmethod
    def from_colmap(cls, camera: Camera, cam_from_world: np.ndarray, *, look_at_depth: float = 1.0) -> ViewerCamera:
        """The view of `camera` at pose `cam_from_world` ((3, 4) or (4, 4)); its principal point is
        taken as the image centre (viser's viewport has no off-centre principal point)."""
        T = np.asarray(cam_from_world, np.float64)
        R, t = T[:3, :3], T[:3, 3]
        centre = -R.T @ t
        forward, down = R[2], R[1]
        return cls(position=centre, look_at=centre + look_at_depth * forward, up=-down,
                   fov_y_rad=float(2.0 * np.arctan(0.5 * camera.height / camera.fy)))

    def url_query(self) -> str:
        """The viser client's URL parameters for this initial camera."""
        def vec(v):
            return ",".join(f"{float(x):.9g}" for x in v)

        return (f"initialCameraPosition={vec(self.position)}&initialCameraLookAt={vec(self.look_at)}"
                f"&initialCameraUp={vec(self.up)}&initialCameraFov={self.fov_y_rad:.9g}")


def viewer_arrays(model: GaussianModel) -> dict[str, np.ndarray]:
    """viser's Gaussian arrays: centers (N, 3), covariances (N, 3, 3), rgbs (N, 3) in [0, 1],
    opacities (N, 1); all float32."""
    with torch.no_grad():
        means = model.means.detach().double().cpu().numpy()
        q = model.quats.detach().double().cpu().numpy()
        scales = np.exp(model.log_scales.detach().double().cpu().numpy())
        rgb = 0.5 + SH_C0 * model.sh0.detach().double().cpu().numpy()[:, 0, :]
        opacity = torch.sigmoid(model.opacity_logits.detach().double()).cpu().numpy()
    bad = [name for name, v in (("means", means), ("quats", q), ("log_scales", scales), ("sh0", rgb),
                                ("opacity_logits", opacity)) if not np.isfinite(v).all()]
    if bad:  # viser would cast NaN colours and opacities to an arbitrary byte without a word
        raise InputError(f"the model's {', '.join(bad)} contain NaN or inf (or scales beyond float range); it "
                         "cannot be viewed", fix="re-train, or view an earlier checkpoint")
    R = R_from_quat(q / np.linalg.norm(q, axis=1, keepdims=True))  # (N, 3, 3)
    cov = np.einsum("nij,nj,nkj->nik", R, scales ** 2, R)
    return {"centers": means.astype(np.float32), "covariances": cov.astype(np.float32),
            "rgbs": np.clip(rgb, 0.0, 1.0).astype(np.float32), "opacities": opacity[:, None].astype(np.float32)}


def _frustum_scale(model_centers: np.ndarray, centres: np.ndarray) -> float:
    """4 % of the median camera-to-scene distance (frustums visible but not in the way)."""
    target = np.median(model_centers, axis=0) if len(model_centers) else np.zeros(3)
    dist = np.linalg.norm(centres - target, axis=1)
    return float(max(0.04 * np.median(dist), 1e-3)) if len(dist) else 0.1


def _overview(sparse: SparseModel, poses: np.ndarray, centres: np.ndarray, target: np.ndarray) -> ViewerCamera:
    """A view from behind the cameras: their mean centre moved back along their mean viewing direction
    by half its distance to `target` (so the frustums are in view), looking at `target`, with the
    cameras' mean up and the first camera's vertical field of view."""
    first = sparse.cameras[sparse.images[0].camera_id]
    centre = centres.mean(axis=0)
    forward = poses[:, 2, :3].mean(axis=0)
    forward /= max(np.linalg.norm(forward), 1e-12)
    position = centre - 0.5 * np.linalg.norm(target - centre) * forward
    up = -poses[:, 1, :3].mean(axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    return ViewerCamera(position=position, look_at=np.asarray(target, np.float64), up=up,
                        fov_y_rad=float(2.0 * np.arctan(0.5 * first.height / first.fy)))


def add_scene(server, model: GaussianModel, sparse: SparseModel | None = None, *,
              initial: ViewerCamera | None = None) -> None:
    """Put `model` (and `sparse`'s cameras, as frustums named by view) into a `viser.ViserServer`.

    The up direction is the cameras' mean image-up (when there are cameras); the initial viewport
    camera is `initial`, else a view from behind the cameras (`_overview`), else viser's default.
    """
    arrays = viewer_arrays(model)
    server.scene.add_gaussian_splats("/splat", **arrays)
    if sparse is not None and sparse.images:
        poses = np.stack([np.asarray(im.cam_from_world, np.float64)[:3] for im in sparse.images])
        centres = np.einsum("nji,nj->ni", poses[:, :, :3], -poses[:, :, 3])
        up = -poses[:, 1, :3].mean(axis=0)
        if np.linalg.norm(up) > 1e-6:
            server.scene.set_up_direction(tuple(up / np.linalg.norm(up)))
        scale = _frustum_scale(arrays["centers"], centres)
        for im, centre in zip(sparse.images, centres, strict=True):
            cam = sparse.cameras[im.camera_id]
            R = np.asarray(im.cam_from_world, np.float64)[:3, :3]
            server.scene.add_camera_frustum(
                f"/cameras/{Path(im.name).stem}", fov=float(2.0 * np.arctan(0.5 * cam.height / cam.fy)),
                aspect=cam.width / cam.height, scale=scale, thickness=0.02 * scale, color=(255, 140, 0),
                wxyz=tuple(quat_from_R(R.T)), position=tuple(centre))
        if initial is None:
            initial = _overview(sparse, poses, centres, np.median(arrays["centers"], axis=0))
    if initial is not None:
        server.initial_camera.position = tuple(initial.position)
        server.initial_camera.look_at = tuple(initial.look_at)
        server.initial_camera.up = tuple(initial.up)
        server.initial_camera.fov = initial.fov_y_rad


def _viser():
    try:
        import viser
    except ImportError as exc:  # a dependency of the project; missing only in a broken environment
        raise InputError("the viewer needs the `viser` package", fix="run `make env` (it installs viser)") from exc
    return viser


def check_listen_address(host: str, port: int) -> None:
    """Refuse a host the viewer could not listen on, before the server starts: viser binds in a thread of its
    own and, where binding fails, tries the next ports for ever, so an unknown host, or an address that is
    not this machine's, left a process waiting with no message. A busy port is not refused: viser serves on
    the next free one and `serve` prints the one it took.

    Raises:
        InputError: `--host` does not resolve, or is not an address of this machine; `--port` is not a port.
    """
    host_fix = "pass an address of this machine as --host (127.0.0.1, the default; 0.0.0.0 for every interface)"
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OverflowError:
        raise InputError(f"--port {port} is not a TCP port", fix="pass a port from 0 to 65535") from None
    except (socket.gaierror, UnicodeError) as exc:
        raise InputError(f"cannot listen on host {host!r}: {exc}", fix=host_fix) from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        try:
            s.bind((addr[0], 0, *addr[2:]))  # any free port: only the host is tested here
        except OSError as exc:
            raise InputError(f"cannot listen on host {host!r}: {exc.strerror or exc}", fix=host_fix) from None


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def viewer_page(model: GaussianModel, sparse: SparseModel | None = None, *,
                initial: ViewerCamera | None = None) -> str:
    """The offline viewer page (viser's client with the scene embedded) as an HTML string.

    A viser server on a free 127.0.0.1 port holds the scene while it is serialised and is
    stopped before returning.
    """
    viser = _viser()
    with contextlib.redirect_stdout(io.StringIO()):  # viser's start/stop banners
        server = viser.ViserServer(host="127.0.0.1", port=_free_port("127.0.0.1"), verbose=False)
        try:
            add_scene(server, model, sparse, initial=initial)
            return server.get_scene_serializer().as_html()
        finally:
            server.stop()


def write_view_folder(folder: str | Path, page: str) -> Path:
    """Write `folder/index.html` (`page`) and `folder/NOTICE.txt` into an existing folder; return index.html."""
    folder = Path(folder)
    (folder / "index.html").write_text(page, encoding="utf-8")
    (folder / "NOTICE.txt").write_text(VIEW_NOTICE, encoding="utf-8")
    return folder / "index.html"


def export_html(model: GaussianModel, out: OutputPlan | str | Path, *, sparse: SparseModel | None = None,
                initial: ViewerCamera | None = None, overwrite: bool = False) -> Path:
    """Write the folder `out` with `index.html` (the offline viewer) and `NOTICE.txt`, atomically.

    `out` follows the output policy of `splat export` (`mvgeo.common.output`): a plan made by the
    caller, or a path checked here (a previous `splat export` folder is replaced only with
    `overwrite`).

    Returns:
        the `index.html` path.
    """
    plan = as_output_plan(out, command="splat export", overwrite=overwrite)
    page = viewer_page(model, sparse, initial=initial)
    with atomic_output_dir(plan) as tmp:
        write_view_folder(tmp, page)
    return plan.path / "index.html"


def serve(model: GaussianModel, sparse: SparseModel | None = None, *, host: str = "127.0.0.1", port: int = 8080,
          stop: threading.Event | None = None) -> None:
    """Serve the scene live on http://host:port until Ctrl-C (or until `stop` is set)."""
    viser = _viser()
    check_listen_address(host, port)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    stop = stop or threading.Event()
    try:
        add_scene(server, model, sparse)
        print(f"viewer: http://{host}:{server.get_port()}  (Ctrl-C to stop)", flush=True)
        while not stop.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()

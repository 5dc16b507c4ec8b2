"""Pictures of a flight in motion: a video of the deforming drone and a mesh series for ParaView.

A flight records the simulator's vertex positions (the FEM nodes) every few control steps
(``sdexp.control.rollout.FrameRecorder``); from those frames

* ``write_animation`` draws the drone's surface with matplotlib -- 3D: the boundary triangles
  (for quadratic elements the subfaces through the mid-edge nodes, ``drone.boundary``), coloured
  by how far each point is from the body's rigid motion (the best-fit rotation and translation
  of the rest shape, mass-weighted) or by height, lit from a fixed direction; 2D: the outline --
  into an MP4 (H.264 through imageio-ffmpeg, which ships its own ffmpeg) or, where ffmpeg is
  not available, a GIF. The axes are fixed: they cover the whole flight (and the obstacles
  within reach) when it stays within a few body sizes, otherwise a window of fixed size follows
  the drone. ``Painter`` draws one frame of it; ``LivePicture`` draws the drone one state at a
  time as it flies (the Gymnasium environments' ``render()``).
* ``write_vtu_series`` writes one ``.vtu`` per frame (the FEM elements, meshio) and a ``.pvd``
  collection with their times, which ParaView opens as one time series.

``save_flight`` does both for a runner (``experiment.params.animate``).
"""
from __future__ import annotations

import functools
import logging
import os
import shutil
import subprocess
import textwrap
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

log = logging.getLogger(__name__)

FRAME_RATE = 25.0            # frames per simulated second, recorded and played
SIZE = (640, 480)            # pixels (multiples of 16: H.264 takes them as they are)
DPI = 100
FOLLOW_FACTOR = 4.0          # a flight spanning more than this x the body's size: the view follows it
LIVE_DEFORMATION = 0.02      # the colour scale of live pictures (LivePicture): 0 to this fraction of the body's size
DEFORMATION_LABEL = "distance from the rigid motion (cm)"

# VTK cell types by nodes per element (meshio's names; the simulator keeps VTK's node order)
_CELL_TYPES = {2: "line", 3: "triangle", 4: "tetra", 6: "triangle6", 10: "tetra10"}


# ------------------------------------------------------------------------------------ ParaView

def _cell_blocks(cells, dim: int) -> list[tuple[str, np.ndarray]]:
    if isinstance(cells, dict):
        return [(k, np.asarray(v)) for k, v in cells.items()]
    if isinstance(cells, (list, tuple)) and cells and isinstance(cells[0], tuple):
        return [(k, np.asarray(v)) for k, v in cells]
    cells = np.asarray(cells, dtype=np.int32)
    k = cells.shape[1]
    if k == 4 and dim == 2:
        raise ValueError("4-node cells of a 2D mesh are ambiguous: pass [('quad', cells)]")
    if k not in _CELL_TYPES:
        raise ValueError(f"cells with {k} nodes: no VTK type known (allowed {sorted(_CELL_TYPES)})")
    return [(_CELL_TYPES[k], cells)]


def write_vtu_series(folder, points_seq, cells, times, point_data=None, name: str | None = None,
                     dtype=np.float64) -> Path:
    """One ``<name>_<i>.vtu`` per frame in ``folder`` and ``<name>.pvd`` listing them with their
    times (``name``: the folder's name); returns the .pvd's path.

    points_seq (n_frames, nv, dim) positions (2D points get z = 0); cells (ne, k) node indices in
    VTK order (k = 4 / 10: linear / quadratic tets, 3 / 6: triangles, 2: segments), or
    [(meshio cell type, array), ...]; times (n_frames,) s; point_data {name: (n_frames, nv, ...)};
    dtype: of the positions and the point data as written (float32 halves the files).
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    name = name or folder.name
    points_seq = [np.asarray(p, dtype=dtype) for p in points_seq]
    times = [float(t) for t in times]
    if len(points_seq) != len(times):
        raise ValueError(f"{len(points_seq)} frames but {len(times)} times")
    dim = points_seq[0].shape[1] if points_seq else 3
    blocks = _cell_blocks(cells, dim)
    point_data = {k: np.asarray(v) for k, v in (point_data or {}).items()}
    for k, v in point_data.items():
        if len(v) != len(points_seq):
            raise ValueError(f"point_data[{k!r}] has {len(v)} frames, the positions {len(points_seq)}")
    # the series is written into a temporary folder beside and put in place whole: a disk that
    # fills mid-series leaves no short series with a 0-byte frame, and the old series stays whole
    tmp = folder.parent / f".{folder.name}.{os.getpid()}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        files = [_write_vtu(tmp, folder, f"{name}_{i:05d}.vtu", pts, blocks,
                            {k: v[i] for k, v in point_data.items()}, dtype) for i, pts in enumerate(points_seq)]
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
        lines += [f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(f)}/>' for t, f in zip(times, files)]
        lines += ["  </Collection>", "</VTKFile>", ""]
        pvd = folder / f"{name}.pvd"
        try:
            (tmp / pvd.name).write_text("\n".join(lines))
        except OSError as err:
            err.filename = str(pvd)
            raise
        _replace_folder(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return pvd


def _write_vtu(tmp: Path, folder: Path, fname: str, pts, blocks, point_data: dict, dtype) -> str:
    """One frame into ``tmp`` (2D points and vectors get z = 0); an error names it in ``folder``."""
    import meshio
    if pts.shape[1] == 2:
        pts = np.c_[pts, np.zeros(len(pts), dtype=dtype)]
    data = {}
    for k, v in point_data.items():
        d = np.asarray(v, dtype=dtype)
        data[k] = np.c_[d, np.zeros(len(d), dtype=dtype)] if d.ndim == 2 and d.shape[1] == 2 else d
    try:
        meshio.write(tmp / fname, meshio.Mesh(pts, blocks, point_data=data), file_format="vtu",
                     binary=True, compression="zlib")
    except OSError as err:
        err.filename = str(folder / fname)   # the file the user would look for
        raise
    return fname


def _replace_folder(new: Path, folder: Path) -> None:
    """``new``'s contents in place of ``folder``'s (a shorter series written there before goes)."""
    if folder.exists():
        old = folder.parent / f".{folder.name}.{os.getpid()}.old"
        os.replace(folder, old)
        os.replace(new, folder)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(new, folder)


def read_pvd(path) -> list[tuple[float, str]]:
    """(time, file) of every frame a .pvd lists."""
    import xml.etree.ElementTree as ET
    root = ET.parse(path).getroot()
    return [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]


# ------------------------------------------------------------------------------------ geometry

def rigid_fit(frames: np.ndarray, rest: np.ndarray, weights=None) -> np.ndarray:
    """The rest shape moved by the best-fit (weighted least squares) rotation and translation
    onto each frame: (n_frames, nv, dim) (Kabsch, batched)."""
    frames = np.asarray(frames, dtype=float)
    rest = np.asarray(rest, dtype=float)
    w = np.ones(len(rest)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    c0 = w @ rest
    c = np.einsum("n,fnd->fd", w, frames)
    a = rest - c0
    h = np.einsum("n,ni,fnj->fij", w, a, frames - c[:, None, :])   # sum w a b^T
    u, _, vt = np.linalg.svd(h)
    det = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", vt, u)))
    d = np.ones((len(frames), rest.shape[1]))
    d[:, -1] = det
    r = np.einsum("fji,fj,fkj->fik", vt, d, u)                       # V diag(d) U^T
    return np.einsum("fij,nj->fni", r, a) + c[:, None, :]


def deformation(frames: np.ndarray, rest: np.ndarray, weights=None) -> np.ndarray:
    """Each node's distance (m) from where the rigid motion would put it: (n_frames, nv)."""
    frames = np.asarray(frames, dtype=float)
    return np.linalg.norm(frames - rigid_fit(frames, rest, weights), axis=-1)


def _boxes(obstacles) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for b in obstacles or []:
        lo, hi = (b["min"], b["max"]) if isinstance(b, dict) else \
            ((b.min, b.max) if hasattr(b, "min") else b)
        out.append((np.asarray(list(lo), dtype=float), np.asarray(list(hi), dtype=float)))
    return out


def _box_faces(lo: np.ndarray, hi: np.ndarray) -> list[np.ndarray]:
    c = np.array([[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]], [hi[0], hi[1], lo[2]], [lo[0], hi[1], lo[2]],
                  [lo[0], lo[1], hi[2]], [hi[0], lo[1], hi[2]], [hi[0], hi[1], hi[2]], [lo[0], hi[1], hi[2]]])
    quads = [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [1, 2, 6, 5], [0, 3, 7, 4]]
    return [c[q] for q in quads]


def _clip(boxes, lo, hi):
    """The parts of the boxes inside [lo, hi] (empty ones dropped)."""
    out = []
    for blo, bhi in boxes:
        a, b = np.maximum(blo[: len(lo)], lo), np.minimum(bhi[: len(hi)], hi)
        if np.all(b > a):
            out.append((a, b))
    return out


class _View:
    """Fixed axes for the whole animation. cover: limits around every frame (and nothing moves
    but the drone); follow: a window of fixed size around the drone, which is drawn relative to
    its centre (the axes read "relative to the centre", the centre's position is printed)."""

    def __init__(self, frames: np.ndarray, rest: np.ndarray, view: str):
        body = float(np.ptp(rest, axis=0).max())
        lo, hi = frames.min(axis=(0, 1)), frames.max(axis=(0, 1))
        if view == "auto":
            view = "follow" if float((hi - lo).max()) > FOLLOW_FACTOR * body else "cover"
        if view not in ("cover", "follow"):
            raise ValueError(f"view = {view!r}: allowed auto, cover, follow")
        self.mode = view
        if view == "cover":
            centre, span = 0.5 * (lo + hi), hi - lo
            # each axis at least half the largest span: a flat flight is not drawn as a sliver
            half = 0.54 * np.maximum(span, 0.5 * float(span.max()))
        else:
            centre, half = np.zeros(len(lo)), np.full(len(lo), 0.75 * body)
        self.lo, self.hi = centre - half, centre + half

    def offset(self, pts: np.ndarray) -> np.ndarray:
        if self.mode == "cover":
            return np.zeros(pts.shape[1])
        return 0.5 * (pts.min(axis=0) + pts.max(axis=0))


# ------------------------------------------------------------------------------------ video

@functools.lru_cache(maxsize=1)
def _ffmpeg_available() -> bool:
    """imageio-ffmpeg's ffmpeg binary (or the one it is pointed at) is there and runs."""
    try:
        import imageio_ffmpeg
        exe = imageio_ffmpeg.get_ffmpeg_exe()
        return subprocess.run([exe, "-version"], capture_output=True, timeout=30).returncode == 0
    except Exception:   # noqa: BLE001 - no package, no binary, not runnable: GIF instead
        return False


class _Sink:
    """Frames (H, W, 3 uint8) into an MP4 (streamed through ffmpeg) or a GIF."""

    def __init__(self, path: Path, fps: float):
        import imageio.v2 as imageio
        self.path, self.fps, self.gif = path, fps, []
        self.writer = None
        if path.suffix.lower() == ".mp4" and not _ffmpeg_available():
            self.path = path.with_suffix(".gif")
            log.warning(f"sdexp: ffmpeg is not available (pip install imageio-ffmpeg): writing "
                        f"{self.path.name} instead of {path.name}")
        # written under a temporary name beside (ffmpeg picks the container by its suffix) and
        # renamed when complete: a video cut short by a full disk never takes the final name
        self.tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp{self.path.suffix}")
        if self.path.suffix.lower() == ".mp4":
            self.writer = imageio.get_writer(self.tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                             quality=6, pixelformat="yuv420p", macro_block_size=16,
                                             ffmpeg_log_level="error")

    def add(self, frame: np.ndarray) -> None:
        if self.writer is not None:
            self.writer.append_data(frame)
        else:
            self.gif.append(frame[::2, ::2].copy())   # GIFs are big: half the size

    def close(self, complete: bool = True) -> Path:
        """Finish the file and give it its name (``complete``), or remove what was written."""
        try:
            if self.writer is not None:
                self.writer.close()
            elif complete:
                import imageio.v3 as iio
                iio.imwrite(self.tmp, np.stack(self.gif), extension=".gif", plugin="pillow",
                            duration=1000.0 / self.fps, loop=0)
            if complete:
                os.replace(self.tmp, self.path)
        except OSError as err:
            err.filename = str(self.path)
            raise
        finally:
            self.tmp.unlink(missing_ok=True)
        return self.path


def write_animation(path, frames, times, faces, *, rest=None, weights=None, obstacles=None, title: str = "",
                    color: str = "deformation", view: str = "auto", fps: float | None = None,
                    size: tuple[int, int] = SIZE, progress: bool = True) -> Path:
    """Draw the drone in every frame into ``path`` (.mp4, or .gif); returns the path written
    (a .gif beside the asked .mp4 when ffmpeg is not available).

    frames (n_frames, nv, dim) node positions; times (n_frames,) s; faces: the boundary
    triangles (3D) or segments (2D) (``drone.boundary``); rest (nv, dim) and weights (nv,) (the
    nodal masses): the rest shape whose rigid motion ``color="deformation"`` measures from
    (default: the first frame, equal weights); ``color="height"``: the vertical (y) coordinate;
    obstacles: boxes (``sim.obstacles`` entries, or (min, max) pairs); view: auto | cover |
    follow; fps: playback frames per second (default: the recording's, so it plays in real time).
    """
    from sdexp.log import Phase

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = np.asarray(frames, dtype=float)
    times = np.asarray(times, dtype=float)
    faces = np.asarray(faces)
    if frames.ndim != 3 or len(frames) == 0 or len(frames) != len(times):
        raise ValueError(f"frames {frames.shape} and times {times.shape}: need (n_frames, nv, dim) and (n_frames,)")
    dim = frames.shape[2]
    rest = frames[0] if rest is None else np.asarray(rest, dtype=float)
    if fps is None:
        fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else FRAME_RATE
    face_values, label, norm = _colour(frames, rest, weights, faces, color)
    painter = Painter(dim, faces, _View(frames, rest, view), norm, label, _boxes(obstacles), title, size)
    sink = _Sink(path, fps)
    try:
        phase = Phase(f"animation {path.name}", len(frames), "frames", enabled=progress)
        for i in phase.iterate(range(len(frames))):
            sink.add(painter.paint(frames[i], face_values[i], times[i]))
    except BaseException:
        sink.close(complete=False)
        raise
    return sink.close()


class Painter:
    """Pictures of the drone one frame at a time (write_animation's, an environment's render()):
    the figure with everything but the drone and the clock drawn once, each frame blitted on it."""

    def __init__(self, dim: int, faces, scope: _View, norm, label: str, boxes=(), title: str = "",
                 size: tuple[int, int] = SIZE):
        import matplotlib
        self.cmap, self.norm, self.scope = matplotlib.colormaps["viridis"], norm, scope
        self.fig, self.canvas, self.draw, self.clock, self.background = _figure(
            dim, faces, list(boxes), scope, self.cmap, norm, label, title, size)

    def paint(self, pts: np.ndarray, face_values: np.ndarray, t: float) -> np.ndarray:
        """The drone at node positions ``pts`` (nv, dim), its faces coloured by ``face_values``,
        at time ``t``: a new (H, W, 3) uint8 image."""
        self.canvas.restore_region(self.background)
        shift = self.scope.offset(pts)
        self.draw.frame(pts - shift, self.cmap(self.norm(face_values)), shift)
        where = "" if self.scope.mode == "cover" else "   centre (" + ", ".join(f"{v:.2f}" for v in shift) + ") m"
        self.clock.set_text(f"t = {t:6.2f} s{where}")
        self.fig.draw_artist(self.clock)
        return np.array(np.asarray(self.canvas.buffer_rgba())[..., :3])


class LivePicture:
    """Pictures of a drone as it flies, one state at a time, for a loop that does not know its
    frames in advance (sdexp.envs' render()): the view follows the drone (a window of fixed size
    about it, its centre printed), the colour is each point's distance from the body's rigid
    motion on a fixed scale (0 to LIVE_DEFORMATION of its size: the colours of one episode and the
    next compare)."""

    def __init__(self, drone, title: str = "", obstacles=None, size: tuple[int, int] = SIZE):
        import matplotlib
        fem = drone.fem
        self.rest, self.weights, self.faces = fem.rest, fem.mass, np.asarray(drone.boundary)
        body = float(np.ptp(self.rest, axis=0).max())
        norm = matplotlib.colors.Normalize(0.0, 100.0 * LIVE_DEFORMATION * body)
        self.painter = Painter(self.rest.shape[1], self.faces, _View(self.rest[None], self.rest, "follow"),
                               norm, DEFORMATION_LABEL, _boxes(obstacles), title, size)

    def __call__(self, pts: np.ndarray, t: float) -> np.ndarray:
        """The (H, W, 3) uint8 picture of the drone at node positions ``pts`` at time ``t``."""
        values = 100.0 * deformation(pts[None], self.rest, self.weights)[0]      # cm
        return self.painter.paint(pts, values[self.faces].mean(axis=1), t)



def _colour(frames, rest, weights, faces, color: str):
    """Each face's value in every frame, the colour bar's label and its normalisation."""
    import matplotlib
    if color == "deformation":
        values = 100.0 * deformation(frames, rest, weights)      # cm
        label = DEFORMATION_LABEL
    elif color == "height":
        values = frames[..., 1]
        label = "height y (m)"
    else:
        raise ValueError(f"color = {color!r}: allowed deformation, height")
    face_values = values[:, faces].mean(axis=2)                    # (n_frames, nf)
    vmin, vmax = (0.0, max(float(face_values.max()), 1e-3)) if color == "deformation" else \
        (float(face_values.min()), max(float(face_values.max()), float(face_values.min()) + 1e-3))
    return face_values, label, matplotlib.colors.Normalize(vmin, vmax)


def _figure(dim: int, faces, boxes, scope, cmap, norm, label: str, title: str, size: tuple[int, int]):
    """The figure with everything but the drone, the obstacles and the clock drawn once (blitting):
    (figure, canvas, drawer, clock text, background)."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    w, h = size
    fig = Figure(figsize=(w / DPI, h / DPI), dpi=DPI)
    canvas = FigureCanvasAgg(fig)
    draw = (_Draw3D if dim == 3 else _Draw2D)(fig, faces, boxes, scope)
    bar = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), cax=fig.add_axes((0.88, 0.18, 0.022, 0.64)))
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=7)
    if title:
        fig.suptitle("\n".join(textwrap.fill(line, 90) for line in title.splitlines()), fontsize=10)
    clock = fig.text(0.01, 0.015, "", fontsize=9, family="monospace", animated=True)
    canvas.draw()
    return fig, canvas, draw, clock, canvas.copy_from_bbox(fig.bbox)


class _Draw3D:
    """The surface as lit, coloured triangles (the ones facing away culled: the surface is
    closed and oriented outward), the obstacles as translucent boxes, each box drawn before or
    after the drone by its depth."""
    LIGHT = np.array([0.3, 1.0, 0.5]) / np.linalg.norm([0.3, 1.0, 0.5])
    WALL = dict(facecolors=(0.45, 0.45, 0.5, 0.3), edgecolors=(0.3, 0.3, 0.35, 0.6), linewidths=0.6)

    def __init__(self, fig, faces, boxes, scope: _View):
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection
        self.ax = ax = fig.add_axes((0.0, 0.03, 0.84, 0.9), projection="3d")
        ax.view_init(elev=22, azim=-60, vertical_axis="y")   # world +y is up
        rel = "" if scope.mode == "cover" else " - centre"
        for axis in "xyz":
            getattr(ax, f"set_{axis}label")(f"{axis}{rel} (m)", labelpad=-4, fontsize=8)
        ax.tick_params(labelsize=7, pad=-2)
        ax.set_xlim(scope.lo[0], scope.hi[0])
        ax.set_ylim(scope.lo[1], scope.hi[1])
        ax.set_zlim(scope.lo[2], scope.hi[2])
        ax.set_box_aspect(scope.hi - scope.lo, zoom=1.0)
        self.faces, self.boxes, self.scope = faces, boxes, scope
        self.surface = Poly3DCollection([], linewidths=0.0, antialiased=False, animated=True)
        self.walls = [Poly3DCollection([], animated=True, **self.WALL) for _ in range(2)]   # behind, in front
        for c in (self.walls[0], self.surface, self.walls[1]):
            ax.add_collection3d(c)

    def _depth(self, pts):
        from mpl_toolkits.mplot3d import proj3d
        return proj3d.proj_transform(pts[:, 0], pts[:, 1], pts[:, 2], self.ax.M)

    def frame(self, pts, colors, shift):
        ax = self.ax
        px, py, pz = self._depth(pts)
        f = self.faces
        area = (px[f[:, 1]] - px[f[:, 0]]) * (py[f[:, 2]] - py[f[:, 0]]) - \
            (py[f[:, 1]] - py[f[:, 0]]) * (px[f[:, 2]] - px[f[:, 0]])
        front = area > 0
        tri = pts[f[front]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        colors = colors[front].copy()
        colors[:, :3] *= (0.45 + 0.55 * np.abs(n @ self.LIGHT))[:, None]   # Lambert, ambient 0.45
        self.surface.set_verts(tri)
        self.surface.set_facecolor(colors)
        if self.boxes:
            moved = [(a - shift, b - shift) for a, b in self.boxes]
            clipped = _clip(moved, self.scope.lo, self.scope.hi)
            centres = np.array([0.5 * (a + b) for a, b in clipped]).reshape(-1, 3)
            drone = float(np.mean(pz))
            box_z = self._depth(centres)[2] if len(clipped) else []
            for k, side in enumerate((box_z > drone, box_z <= drone) if len(clipped) else ((), ())):
                self.walls[k].set_verts([q for (a, b), s in zip(clipped, side) if s for q in _box_faces(a, b)])
        for c in (self.walls[0], self.surface, self.walls[1]):
            c.do_3d_projection()
            ax.draw_artist(c)


class _Draw2D:
    """The outline (boundary segments) coloured per segment; obstacles as rectangles."""

    def __init__(self, fig, faces, boxes, scope: _View):
        from matplotlib.collections import LineCollection, PatchCollection
        self.ax = ax = fig.add_axes((0.1, 0.12, 0.72, 0.78))
        ax.set_aspect("equal")
        rel = "" if scope.mode == "cover" else " - centre"
        ax.set_xlabel(f"x{rel} (m)")
        ax.set_ylabel(f"y{rel} (m)")
        ax.grid(alpha=0.3)
        ax.set_xlim(scope.lo[0], scope.hi[0])
        ax.set_ylim(scope.lo[1], scope.hi[1])
        self.faces, self.boxes, self.scope = faces[:, :2], boxes, scope
        self.outline = LineCollection([], linewidths=2.0, animated=True)
        self.walls = PatchCollection([], facecolor=(0.45, 0.45, 0.5, 0.35), edgecolor=(0.3, 0.3, 0.35),
                                     animated=True)
        ax.add_collection(self.walls)
        ax.add_collection(self.outline)

    def frame(self, pts, colors, shift):
        from matplotlib.patches import Rectangle
        self.outline.set_segments(pts[self.faces])
        self.outline.set_color(colors)
        if self.boxes:
            moved = [(a[:2] - shift, b[:2] - shift) for a, b in self.boxes]
            self.walls.set_paths([Rectangle(a, *(b - a)) for a, b in _clip(moved, self.scope.lo, self.scope.hi)])
            self.ax.draw_artist(self.walls)
        self.ax.draw_artist(self.outline)


# ------------------------------------------------------------------------------------ runners

def save_flight(out_dir, stem: str, recorder, drone, obstacles=None, title: str = "",
                progress: bool = True, paraview: bool = False) -> dict[str, Path]:
    """A runner's pictures of one recorded flight: ``<stem>.mp4`` (or .gif) and the ParaView
    series ``<stem>_vtu/<stem>.pvd`` if ``paraview`` (the FEM elements, with each node's displacement from the
    rigid motion as point data ``deformation``; single precision, about 110 kB a frame for the
    flower's 2887 nodes)."""
    import time

    out_dir = Path(out_dir)
    if not recorder.points:
        log.warning(f"sdexp: {stem}: no frames recorded, no animation")
        return {}
    frames = np.stack(recorder.points)
    times = np.asarray(recorder.times)
    fem = drone.fem
    out = {}
    # the flight's numbers are written whatever becomes of its pictures, except on a full disk,
    # where they could not be written either (a UserError naming the file, the run stops)
    t0 = time.perf_counter()
    out["video"] = _picture(stem, "video", out_dir / f"{stem}.mp4", lambda: write_animation(
        out_dir / f"{stem}.mp4", frames, times, drone.boundary, rest=fem.rest, weights=fem.mass,
        obstacles=obstacles, title=title, fps=recorder.frame_rate, progress=progress))
    t1 = time.perf_counter()
    if paraview:   # opt-in: 57 MB for a 20 s flower flight, against 0.4 MB of video
        fitted = rigid_fit(frames, fem.rest, fem.mass)
        out["pvd"] = _picture(stem, "ParaView series", out_dir / f"{stem}_vtu", lambda: write_vtu_series(
            out_dir / f"{stem}_vtu", frames, fem.elems, times, point_data={"deformation": frames - fitted},
            name=stem, dtype=np.float32))
    took = {"video": t1 - t0, "pvd": time.perf_counter() - t1}
    out = {k: v for k, v in out.items() if v is not None}
    if out:
        log.info(f"sdexp: {stem}: {len(frames)} frames -> " + ", ".join(f"{v} ({took[k]:.1f} s)" for k, v in out.items()))
    return out


def _picture(stem: str, what: str, path: Path, write) -> Path | None:
    """``write()``'s path, or None with a warning naming the file that failed."""
    from sdexp.errors import disk_full
    try:
        return write()
    except (OSError, RuntimeError) as err:
        full = disk_full(err, path, "or choose another folder with hydra.run.dir=<folder>") \
            if isinstance(err, OSError) else None
        if full is not None:
            raise full from None
        failed = getattr(err, "filename", None) or path
        log.warning(f"sdexp: {stem}: the {what} {failed} could not be written ({err}); the flight's numbers are "
                    f"written all the same")
        return None

"""Training data for the learned dynamics (supplement F): generated, cached, split.

A dataset is a set of transitions, one per 10 ms control step, computed from sensor readings
only (noise and delay as configured; how they are generated: sdexp/model/generate.py):

  keys (arrays of float32, first axis N transitions):
    s, s_dot        (N, n_s)   bend angles and rates           (sdexp.sensing.State)
    e, e_dot        (N, n_e)   Euler angles and rates (n_e = 3 in 3D, 1 in 2D)
    p, p_dot        (N, dim)   position and velocity
    u               (N, m)     the commanded thrusts held during the step
    s_dot_next, e_dot_next, p_dot_next   the rates read one control step later
    raw, raw_dot, raw_dot_next (N, n_raw)  the undecomposed state for the decomposition
                    ablation: concat(p, central IMU Euler angles, every peripheral IMU's
                    world-frame Euler angles (2D: angle)) and its rates;
                    n_raw = dim + n_e (1 + n_s)
    episode         (N,) int32 episode index; t (N,) float32 time in the episode

Within an episode, transition k+1's state is read from the same (noisy) readings as transition
k's ``*_next`` rates, so ``p_dot[k + 1] == p_dot_next[k]``. Angles are stored as read, not
unwrapped: yaw e_y, 2D angles and the peripheral Euler angles jump by 2 pi where they pass
+-pi, and Euler rates grow large near the gimbal lock (|e_z| -> 90 deg, a drone on its side).

Generation runs in fixed chunks of ``chunk_samples`` transitions, each a pure function of the
config, the seed and its index (see generate.py), on ``data.workers`` processes; the data is
the same whatever the number of workers. Each chunk is written atomically to
``<cache_dir>/<key>.chunks/`` as it finishes, so a killed run resumes with the chunks it has;
the merged ``<cache_dir>/<key>.npz`` is written atomically and the chunk folder removed. The key
hashes the drone, sim (without obstacles: the data are free flights), noise and data (less
``validation_fraction``: the split is made after loading) configs' key fields (sdexp.cache.config_key:
no thread or worker counts), the seed, the chunk size and DATA_FORMAT. A cache file whose format,
key or arrays do not match is regenerated with a warning, never read.

Not covered by the key: the simulator's code. After changing sdexp/sim/ in a way that changes
its output, bump DATA_FORMAT (or clear the cache).
"""
from __future__ import annotations

import json
import logging
import math
import shutil
import time
import zipfile
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sdexp.cache import atomic_write, build_lock, config_key, key_of
from sdexp.errors import UserError
from sdexp.parallel import run_spawned

log = logging.getLogger(__name__)


KEYS = ("s", "s_dot", "e", "e_dot", "p", "p_dot", "u", "s_dot_next", "e_dot_next", "p_dot_next",
        "raw", "raw_dot", "raw_dot_next", "episode", "t")

DATA_FORMAT = 4  # 2: continuous bend angle s (sdexp.sensing); 3: the key from the configs' key fields;
                 # 4: rotor thrust as a traction over its disc (sim.mesh.traction)
# transitions per chunk (at least one episode's length): small enough to balance two workers
# and lose little to a kill, big enough that few episodes are cut at a chunk's end
CHUNK_SAMPLES = 4000
FAILURES = ("inverted_element", "non_finite", "runaway_speed", "runaway_extent")


@dataclass
class Dataset:
    arrays: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)  # drone, dim, n_s, n_e, m, control_dt, samples/s

    def __len__(self) -> int:
        return len(self.arrays["u"])

    def joined(self, arrays: dict[str, np.ndarray], label: str) -> "Dataset":
        """This dataset and ``arrays`` (the same keys; their episodes numbered after this one's)."""
        extra = {**arrays, "episode": arrays["episode"] + int(self.arrays["episode"].max()) + 1}
        out = {k: np.concatenate([v, extra[k].astype(v.dtype)]) for k, v in self.arrays.items()}
        return Dataset(out, {**self.meta, "joined": [*self.meta.get("joined", []), f"{label}: {len(arrays['u'])} transitions"]})

    def split(self, validation_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(train, validation) transition indices, split by whole episodes: episodes in a random
        order (``seed``) go to validation until it holds the count closest to
        ``validation_fraction`` of the transitions (at least one episode, and at least one left
        for training)."""
        episode = self.arrays["episode"]
        ids, counts = np.unique(episode, return_counts=True)
        if len(ids) < 2:
            raise UserError(f"the dataset holds {len(ids)} episode(s): a split by episodes needs two; "
                            "raise data.samples")
        order = np.random.default_rng(seed).permutation(len(ids))
        cum = np.cumsum(counts[order])
        n_val = int(np.argmin(np.abs(cum - validation_fraction * len(episode)))) + 1
        n_val = min(max(n_val, 1), len(ids) - 1)
        val = np.isin(episode, ids[order[:n_val]])
        return np.flatnonzero(~val), np.flatnonzero(val)


# ------------------------------------------------------------------------------ config -> key

def dataset_spec(cfg, chunk_samples: int | None = None) -> dict:
    """Everything that determines the data (plus ``cache_dir``, which does not): the drone, sim,
    noise and data configs (dataclasses), the seed and the chunk size."""
    data = cfg.data
    if chunk_samples is None:
        steps = int(round(data.episode_seconds / cfg.sim.control_dt))
        chunk_samples = max(CHUNK_SAMPLES, steps)
    return {
        "drone": cfg.drone,
        # a task's scenery left out: the data are free flights (supplement F); on data.sim_model if set
        "sim": replace(cfg.sim, obstacles=[], model=data.sim_model or cfg.sim.model),
        "noise": cfg.noise,
        # the random holds alone: ours' flights (data.aggregation) join them after, in sdexp.eval.aggregation
        "data": replace(data, aggregation=type(data.aggregation)()),
        "seed": int(cfg.seed),
        "chunk_samples": int(chunk_samples),
        "cache_dir": str(Path(cfg.cache_dir).expanduser()),
    }


def data_key(data) -> dict:
    """The data config's part of the key: the split (``validation_fraction``) is made after loading."""
    return {k: v for k, v in config_key(data).items() if k != "validation_fraction"}


def dataset_key(spec: dict) -> str:
    return key_of("data", DATA_FORMAT, {"drone": config_key(spec["drone"]), "sim": config_key(spec["sim"]),
                                        "noise": config_key(spec["noise"]), "data": data_key(spec["data"]),
                                        "seed": spec["seed"], "chunk_samples": spec["chunk_samples"]})


# ------------------------------------------------------------------------------ files

class _Unusable(Exception):
    """A cache file that must not be read (other format or key, missing arrays, corrupt)."""


def _write_npz(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, __meta__=np.array(json.dumps(meta, default=float)), **arrays)
    atomic_write(path, write)


def _read_npz(path: Path, expect: dict) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays and meta of ``path``; _Unusable unless meta matches ``expect`` (format, key,
    ...), all KEYS are there and every array has meta['samples'] rows."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if "__meta__" not in z.files:
                raise _Unusable("no metadata")
            meta = json.loads(str(z["__meta__"]))
            for k, v in expect.items():
                if meta.get(k) != v:
                    raise _Unusable(f"{k} is {meta.get(k)!r}, expected {v!r}")
            missing = [k for k in KEYS if k not in z.files]
            if missing:
                raise _Unusable(f"missing arrays {missing}")
            arrays = {k: z[k] for k in KEYS}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as err:
        raise _Unusable(f"unreadable ({type(err).__name__}: {err})") from None
    n = meta.get("samples")
    if any(len(a) != n for a in arrays.values()):
        raise _Unusable(f"array lengths differ from samples = {n}")
    return arrays, meta


def _chunk_path(folder: Path, c: int) -> Path:
    return folder / f"chunk-{c:05d}.npz"


def _run_chunk(spec: dict, key: str, c: int, n: int, path: str, progress=None) -> dict:
    """Generate chunk c and write it atomically; returns its summary."""
    from sdexp.model.generate import generate_chunk
    arrays, info = generate_chunk(spec, c, n, progress)
    _write_npz(Path(path), arrays, {"format": DATA_FORMAT, "key": key, "chunk": c, "samples": n, "info": info})
    return info


# ------------------------------------------------------------------------------ generation

def _generate(spec: dict, key: str, final: Path, workers: int) -> Dataset:
    from sdexp.log import Phase

    folder = final.with_suffix(".chunks")
    samples, chunk = int(spec["data"].samples), spec["chunk_samples"]
    sizes = [min(chunk, samples - c * chunk) for c in range(math.ceil(samples / chunk))]
    infos = _finished_chunks(folder, key, sizes)
    resumed = len(infos)
    todo = [c for c in range(len(sizes)) if c not in infos]
    workers = max(1, min(workers, len(todo)))
    if todo:
        from sdexp.model.generate import _simulator, sim_config, thrust_draw
        drone, _ = _simulator(spec)  # mesh once (cached) and fail early on a bad drone, before any worker
        spec = {**spec, "draw": thrust_draw(drone, spec["data"], sim_config(spec), spec["cache_dir"])}  # once, not per worker
    t0 = time.perf_counter()
    # (an error or a kill closes the phase with a line that says it stopped)
    with Phase(f"data generation {spec['drone'].name} ({workers} worker{'s' if workers > 1 else ''})",
               total=samples, initial=sum(sizes[c] for c in infos), unit="samples") as bar:
        if todo and workers == 1:
            for c in todo:
                infos[c] = _run_chunk(spec, key, c, sizes[c], str(_chunk_path(folder, c)), bar.update)
        elif todo:
            _run_pool(spec, key, folder, sizes, todo, workers, infos, bar)
    wall = time.perf_counter() - t0
    merged = _merge(folder, final, key, sizes, samples)
    if isinstance(merged, Dataset):   # another process merged first
        return merged
    arrays, episodes = merged
    ends = sum((Counter(infos[c]["ends"]) for c in infos), Counter())
    generated = sum(sizes[c] for c in todo)
    d = spec["drone"]
    meta = {
        "format": DATA_FORMAT, "key": key, "samples": samples,
        "drone": d.name, "dim": int(d.dim), "n_s": arrays["s"].shape[1], "n_e": arrays["e"].shape[1],
        "m": arrays["u"].shape[1], "n_raw": arrays["raw"].shape[1], "control_dt": float(spec["sim"].control_dt),
        "max_thrust": float(d.max_thrust), "noise": bool(spec["noise"].enabled),
        "seed": spec["seed"], **{f"data_{k}": v for k, v in data_key(spec["data"]).items()},
        "episodes": episodes, "ends": dict(ends),
        "failures": {r: ends.get(r, 0) for r in FAILURES},
        "chunk_samples": chunk, "chunks": len(sizes), "chunks_resumed": resumed, "workers": workers,
        "wall_seconds": wall, "generated_samples": generated,
        "samples_per_second": generated / wall if generated else None,
        # per-chunk sums over the workers: wall time, and CPU time (wall minus time lost to
        # other processes on the same cores)
        "worker_seconds": sum(infos[c]["seconds"] for c in todo),
        "worker_cpu_seconds": sum(infos[c]["cpu_seconds"] for c in todo),
        "raw_layout": "p (dim), frame Euler angles e (n_e), then each peripheral IMU's world-frame "
                      "Euler angles (n_e each, 2D: its angle); rates alike; angles not unwrapped",
    }
    _write_npz(final, arrays, meta)
    shutil.rmtree(folder, ignore_errors=True)
    return Dataset(arrays, {**meta, "cached": False})


def _finished_chunks(folder: Path, key: str, sizes: list[int]) -> dict[int, dict]:
    """The summaries of the chunks a killed or earlier run left whole (the caller holds the lock);
    its half-written ones are removed, unusable ones regenerated."""
    infos: dict[int, dict] = {}
    for stale in folder.glob(".*.tmp"):
        stale.unlink(missing_ok=True)
    for c, n in enumerate(sizes):
        path = _chunk_path(folder, c)
        if path.exists():
            try:
                infos[c] = _read_npz(path, {"format": DATA_FORMAT, "key": key, "chunk": c, "samples": n})[1]["info"]
            except _Unusable:
                pass
    return infos


def _merge(folder: Path, final: Path, key: str, sizes: list[int], samples: int):
    """The chunks in order, episode ids made global: (arrays, episodes); or the Dataset another
    process generating the same data merged first (it removed the chunks)."""
    parts, offset = [], 0
    for c, n in enumerate(sizes):
        try:
            arrays, _ = _read_npz(_chunk_path(folder, c), {"format": DATA_FORMAT, "key": key, "chunk": c, "samples": n})
        except _Unusable as err:
            try:
                arrays, meta = _read_npz(final, {"format": DATA_FORMAT, "key": key, "samples": samples})
                return Dataset(arrays, {**meta, "cached": True})
            except _Unusable:
                raise RuntimeError(f"dataset chunk {_chunk_path(folder, c)} vanished or broke while "
                                   f"merging ({err}); run again to regenerate it") from None
        _, local = np.unique(arrays["episode"], return_inverse=True)
        arrays["episode"] = (offset + local.ravel()).astype(np.int32)
        offset = int(arrays["episode"].max()) + 1 if n else offset
        parts.append(arrays)
    return {k: np.concatenate([a[k] for a in parts]) for k in KEYS}, offset


def _run_pool(spec, key, folder, sizes, todo, workers, infos, bar) -> None:
    """Chunks ``todo`` on ``workers`` processes (sdexp.parallel); each writes its own chunk file,
    so the chunks finished before a failure or a kill are kept."""
    tasks = [(spec, key, c, sizes[c], str(_chunk_path(folder, c))) for c in todo]
    for c, info in zip(todo, run_spawned(_chunk_task, tasks, workers, bar.update)):
        infos[c] = info


def _chunk_task(spec, key, c, n, path, report):
    return _run_chunk(spec, key, c, n, path, progress=report)


# ------------------------------------------------------------------------------ entry point

def load_dataset(cfg, chunk_samples: int | None = None) -> Dataset:
    """The dataset for cfg.drone / cfg.sim / cfg.noise / cfg.data / cfg.seed, from the cache
    or generated (``data.workers`` processes, progress bar, atomic and resumable).

    ``chunk_samples`` (default: max(CHUNK_SAMPLES, one episode)) is part of the data's identity;
    tests shrink it. Raises UserError for a drone without peripheral sensors (there is no s for
    d to predict; the method is for soft drones) and for a dataset whose training split cannot
    fill one batch of ``model.batch_size``."""
    d, data, batch = cfg.drone, cfg.data, int(cfg.model.batch_size)
    if int(d.num_sensors) == 0:
        raise UserError(f"drone {d.name} has no peripheral sensors (drone.num_sensors = 0): the "
                        "learned dynamics need the bend angles s; add sensors")
    if data.samples * (1 - data.validation_fraction) < batch:
        raise UserError(f"data.samples = {data.samples} leaves about "
                        f"{int(data.samples * (1 - data.validation_fraction))} training transitions "
                        f"after the validation split, fewer than one batch (model.batch_size = {batch}); "
                        "raise data.samples or lower model.batch_size")
    spec = dataset_spec(cfg, chunk_samples)
    key = dataset_key(spec)
    final = Path(spec["cache_dir"]) / f"{key}.npz"
    ds = None
    if final.exists():
        try:
            arrays, meta = _read_npz(final, {"format": DATA_FORMAT, "key": key, "samples": int(data.samples)})
            ds = Dataset(arrays, {**meta, "cached": True})
        except _Unusable as err:
            log.warning(f"sdexp: dataset cache {final} is unusable ({err}); regenerating")
    if ds is None:
        with build_lock(final):   # concurrent jobs that need this data: one generates, the others wait
            if final.exists():
                try:
                    arrays, meta = _read_npz(final, {"format": DATA_FORMAT, "key": key, "samples": int(data.samples)})
                    ds = Dataset(arrays, {**meta, "cached": True})
                except _Unusable:
                    pass
            if ds is None:
                ds = _generate(spec, key, final, int(data.workers))
    train, val = ds.split(float(data.validation_fraction), int(cfg.seed))
    if len(train) < batch:
        raise UserError(f"data.samples = {data.samples} gives {len(train)} training transitions after "
                        f"the split by episodes, fewer than one batch (model.batch_size = {batch}); "
                        "raise data.samples or lower model.batch_size")
    return ds

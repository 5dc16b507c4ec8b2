"""The measured-log format: one CSV per flight plus ``meta.json`` per folder.

meta.json: ``{"format": "sdexp-flight-log", "version": 1, "drone": <name>, "dim": 2|3,
"sample_rate": <Hz>, "num_rotors": m, "num_sensors": n}`` (extra keys are kept, never read by
the workflow).

Each ``<flight>.csv`` has a header row and one row per control step, columns in any order:

- ``t``: time (s), strictly increasing, spaced 1 / sample_rate;
- ``u0 .. u{m-1}``: the commanded thrust of each rotor (N) issued at t;
- the sensor channels of the sensor pipeline (sdexp.sensing.decompose) read at t:
  ``p_x p_y [p_z]``, ``e_x e_y e_z`` (2D: ``e``), ``s0 .. s{n-1}`` and their rates
  ``p_dot_*``, ``e_dot_*``, ``s_dot*``.

Row i's readings result from the commands of rows < i. A real drone's logs can be written in
this format by anything that computes p, e, s and their rates as the sensor pipeline does.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.cache import atomic_write
from sdexp.errors import UserError

FORMAT = "sdexp-flight-log"
VERSION = 1
META = "meta.json"


def channel_names(dim: int, num_sensors: int) -> list[str]:
    """Sensor columns in the state order (p, e, s, then their rates)."""
    axes = "xyz"[:dim]
    p = [f"p_{a}" for a in axes]
    e = ["e_x", "e_y", "e_z"] if dim == 3 else ["e"]
    s = [f"s{i}" for i in range(num_sensors)]
    rate = lambda names: [n.replace("_", "_dot_", 1) if "_" in n else f"{n}_dot" for n in names]
    return p + e + s + [f"p_dot_{a}" for a in axes] + rate(e) + [f"s_dot{i}" for i in range(num_sensors)]


def thrust_names(num_rotors: int) -> list[str]:
    return [f"u{r}" for r in range(num_rotors)]


def angle_columns(names: list[str]) -> np.ndarray:
    """Mask of the Euler-angle channels (compared modulo 2 pi)."""
    return np.array([n == "e" or (n.startswith("e_") and "dot" not in n) for n in names])


def state_row(st) -> np.ndarray:
    """A sdexp.sensing.State as one row in channel_names order."""
    return np.concatenate([st.p, st.e, st.s, st.p_dot, st.e_dot, st.s_dot])


@dataclass
class Flight:
    name: str
    t: np.ndarray   # (n,)
    u: np.ndarray   # (n, m) commanded thrust
    y: np.ndarray   # (n, C) sensor channels, channel_names order


@dataclass
class Logs:
    folder: Path
    meta: dict
    channels: list[str]
    flights: list[Flight]

    @property
    def dt(self) -> float:
        return 1.0 / float(self.meta["sample_rate"])


def meta_for(drone, sample_rate: float, **extra) -> dict:
    return {"format": FORMAT, "version": VERSION, "drone": drone.name, "dim": drone.dim,
            "sample_rate": float(sample_rate), "num_rotors": drone.num_rotors,
            "num_sensors": drone.layout.n_s, **extra}


def write_meta(folder: Path, meta: dict) -> None:
    atomic_write(Path(folder) / META, lambda tmp: tmp.write_text(json.dumps(meta, indent=2)))


def write_flight(folder: Path, name: str, flight_t, u, y, dim: int, num_sensors: int) -> Path:
    cols = ["t"] + thrust_names(np.shape(u)[1]) + channel_names(dim, num_sensors)
    table = pd.DataFrame(np.c_[flight_t, u, y], columns=cols)
    path = Path(folder) / f"{name}.csv"
    atomic_write(path, lambda tmp: table.to_csv(tmp, index=False, float_format="%.9g"))
    return path


# Largest plausible magnitude of a reading, by channel kind: beyond it no flight of a soft drone
# lies (a 1e308 is a corrupt log, whose squares overflow to infinite losses): (bound, unit, what).
PLAUSIBLE = {
    "t": (1e6, "s", "a log's time"),
    "u": (1e3, "N", "a rotor's commanded thrust"),
    "p": (1e4, "m", "a drone's position"),
    "p_dot": (1e3, "m/s", "a drone's speed"),
    "e": (1e3, "rad", "an Euler angle (yaw unwrapped)"),
    "e_dot": (1e3, "rad/s", "an angular rate"),
    "s": (2 * np.pi, "rad", "a bend angle (atan2, plus noise)"),
    "s_dot": (1e3, "rad/s", "a bend rate"),
}


def channel_kind(name: str) -> str:
    """The PLAUSIBLE key of a log column: t, u, p, p_dot, e, e_dot, s or s_dot."""
    if name == "t":
        return "t"
    if name.startswith("u"):
        return "u"
    for kind in ("p_dot", "e_dot", "s_dot", "p", "e", "s"):
        if name.startswith(kind):
            return kind
    return "t"


def _meta_number(meta_path: Path, meta: dict, key: str, integer: bool = False) -> float:
    value = meta[key]
    try:
        number = float(value)
        if isinstance(value, bool) or not np.isfinite(number) or (integer and number != int(number)):
            raise ValueError
    except (TypeError, ValueError):
        raise UserError(f"{meta_path}: {key} = {value!r} is not {'a whole' if integer else 'a finite'} "
                        f"number") from None
    return int(number) if integer else number


def read_logs(folder, drone_name: str, num_rotors: int, num_sensors: int, dim: int,
              min_rows: int = 2, max_thrust: float | None = None) -> Logs:
    """Read and check a log folder; every problem is a UserError naming the file and column (and
    the row of an implausible reading: PLAUSIBLE, commands beyond 1.5 x ``max_thrust``)."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise UserError(f"discrepancy.measured = {str(folder)!r} is not a folder")
    meta_path = folder / META
    meta, rate = _read_meta(meta_path, drone_name, num_rotors, num_sensors, dim)
    channels = channel_names(dim, num_sensors)
    want = ["t"] + thrust_names(num_rotors) + channels
    files = sorted(folder.glob("*.csv"))
    if not files:
        raise UserError(f"{folder}: no flight CSV files")
    flights = []
    for path in files:
        table = _read_flight_table(path, want, max_thrust)
        if len(table) < min_rows:
            raise UserError(f"{path}: {len(table)} rows, need at least {min_rows}")
        t = table["t"].to_numpy(float)
        _check_spacing(path, meta_path, meta, t, rate)
        flights.append(Flight(path.stem, t, table[thrust_names(num_rotors)].to_numpy(float),
                              table[channels].to_numpy(float)))
    return Logs(folder, meta, channels, flights)


def _read_meta(meta_path: Path, drone_name: str, num_rotors: int, num_sensors: int, dim: int) -> tuple[dict, float]:
    """meta.json, checked against the drone: (meta, sample rate)."""
    if not meta_path.exists():
        raise UserError(f"{meta_path}: missing (the log format needs a meta.json naming the drone and sample rate)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as err:
        raise UserError(f"{meta_path}: not valid JSON ({err})") from None
    for key in ("drone", "sample_rate"):
        if key not in meta:
            raise UserError(f"{meta_path}: missing key {key!r}")
    if meta["drone"] != drone_name:
        raise UserError(f"{meta_path}: logs are of drone {meta['drone']!r} but drone={drone_name!r} was given")
    for key, want in (("num_rotors", num_rotors), ("num_sensors", num_sensors), ("dim", dim)):
        if key in meta and _meta_number(meta_path, meta, key, integer=True) != want:
            raise UserError(f"{meta_path}: {key} = {meta[key]} but drone {drone_name} has {want}")
    rate = _meta_number(meta_path, meta, "sample_rate")
    if not rate > 0:
        raise UserError(f"{meta_path}: sample_rate = {meta['sample_rate']} must be > 0 Hz")
    return meta, rate


def _read_flight_table(path: Path, want: list[str], max_thrust: float | None) -> pd.DataFrame:
    """One flight's CSV with every wanted column, each numeric and plausible."""
    try:
        table = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: cannot be read as CSV ({err})") from None
    missing = [c for c in want if c not in table.columns]
    if missing:
        extra = [c for c in table.columns if c not in want]
        hint = f"; unexpected column(s) {extra} (misnamed?)" if extra else ""
        raise UserError(f"{path}: missing column(s) {missing}{hint}")
    for c in want:
        col = pd.to_numeric(table[c], errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(col))
        if len(bad):
            raise UserError(f"{path}: column {c!r} has {len(bad)} NaN/non-numeric value(s), first at data row {bad[0] + 1}")
        bound, unit, what = PLAUSIBLE[channel_kind(c)]
        if channel_kind(c) == "u" and max_thrust is not None:
            bound, what = 1.5 * float(max_thrust), "a rotor's command (drone.max_thrust x 1.5)"
        wild = np.flatnonzero(np.abs(col) > bound)
        if len(wild):
            i = wild[0]
            raise UserError(f"{path}: column {c!r}, data row {i + 1}: {col[i]:.6g} {unit} is implausible "
                            f"for {what}: allowed |{c}| <= {bound:g} {unit} ({len(wild)} such row(s))")
    return table


def _check_spacing(path: Path, meta_path: Path, meta: dict, t: np.ndarray, rate: float) -> None:
    """Column t strictly increasing and spaced 1 / sample_rate; a flight evenly spaced at another
    rate says that meta.json is what is wrong."""
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise UserError(f"{path}: column 't' is not strictly increasing (data row {np.flatnonzero(dt <= 0)[0] + 2})")
    if np.any(np.abs(dt * rate - 1.0) > 0.01):
        step = float(np.median(dt))
        if np.all(np.abs(dt / step - 1.0) <= 0.01):
            raise UserError(f"{meta_path}: sample_rate = {meta['sample_rate']} Hz contradicts the flights: "
                            f"{path.name}'s column 't' is spaced {step:g} s ({1 / step:g} Hz); allowed the rate "
                            f"the logs were recorded at: set sample_rate to {1 / step:g}")
        raise UserError(f"{path}: column 't' is not spaced 1/sample_rate = {1 / rate:g} s "
                        f"(data row {np.flatnonzero(np.abs(dt * rate - 1.0) > 0.01)[0] + 2})")

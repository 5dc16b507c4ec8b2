"""Where do simulator and logs disagree? Residuals per channel and per flight regime, against
the noise floor: the same short-horizon predictions run on nominal simulated flights.

Regimes are measured at each window's start: speed |p_dot|, height p_y, thrust level (mean
command), bend max|s| and rotation rate |e_dot|; each is split in ``bins`` quantile bins of the
measured windows. A cell's ratio is mean normalised squared residual of the measured windows in
it over that of the floor windows in the same bin (1 = at the noise floor); its z-score comes
from the spread over windows of both.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

REGIMES = ("speed", "height", "thrust", "bend", "rotation")


def regime_values(w, dim: int, n_s: int) -> dict[str, np.ndarray]:
    ne = 3 if dim == 3 else 1
    y = w.start_rows
    i_s = dim + ne
    i_pd = i_s + n_s
    i_ed = i_pd + dim
    return {
        "speed": np.linalg.norm(y[:, i_pd:i_pd + dim], axis=1),
        "height": y[:, 1],
        "thrust": w.start_u.mean(axis=1),
        "bend": np.abs(y[:, i_s:i_s + n_s]).max(axis=1) if n_s else np.zeros(len(y)),
        "rotation": np.linalg.norm(y[:, i_ed:i_ed + ne], axis=1),
    }


def noise_floor(r_floor: np.ndarray) -> np.ndarray:
    """sigma[k, c]: the spread of the nominal simulator's residuals on nominal flights, per
    horizon step and channel, estimated robustly (median of r^2 / 0.455, the median of a
    chi-square with one degree of freedom): a few windows with large errors (a hard landing of
    the pilot, a fast turn) would otherwise set the weight of a whole channel. A tiny floor keeps
    a channel that is predicted exactly from dividing by 0."""
    s = np.sqrt(np.median(r_floor ** 2, axis=0) / 0.455)
    return np.maximum(s, 1e-6 * np.maximum(s.max(axis=0, keepdims=True), 1e-12))


def localize(r_meas: np.ndarray, w_meas, r_floor: np.ndarray, w_floor, sigma: np.ndarray,
             dim: int, n_s: int, bins: int = 3) -> pd.DataFrame:
    """One row per (channel, regime, bin): windows, measured and floor mean normalised squared
    residual, their ratio and z-score; plus a row per channel over all windows (regime 'all')."""
    em = np.mean((r_meas / sigma) ** 2, axis=1)     # (W, C)
    ef = np.mean((r_floor / sigma) ** 2, axis=1)
    vm = regime_values(w_meas, dim, n_s)
    vf = regime_values(w_floor, dim, n_s)
    rows = []

    def cell(sel_m, sel_f, regime, b, lo, hi):
        for c, name in enumerate(w_meas.channels):
            a, f = em[sel_m, c], ef[sel_f, c]
            if len(a) < 2 or len(f) < 2:
                continue
            fm = max(f.mean(), 1e-12)
            se = np.sqrt(a.var(ddof=1) / len(a) + f.var(ddof=1) / len(f))
            rows.append({"channel": name, "regime": regime, "bin": b, "low": lo, "high": hi,
                         "windows": int(len(a)), "measured": float(a.mean()), "floor": float(f.mean()),
                         "ratio": float(a.mean() / fm), "z": float((a.mean() - f.mean()) / max(se, 1e-12))})

    cell(np.ones(len(em), bool), np.ones(len(ef), bool), "all", 0, -np.inf, np.inf)
    for g in REGIMES:
        edges = np.quantile(vm[g], np.linspace(0, 1, bins + 1)) if len(vm[g]) else np.zeros(bins + 1)
        for b in range(bins):
            lo, hi = edges[b], edges[b + 1]
            cell(_in_bin(vm[g], b, bins, lo, hi), _in_bin(vf[g], b, bins, lo, hi), g, b, float(lo), float(hi))
    return pd.DataFrame(rows)


def _in_bin(v, b, bins, lo, hi):
    """Bins are half-open [lo, hi) except that the first and last reach out to +-inf, so floor
    windows outside the measured range still count."""
    sel = np.ones(len(v), bool)
    if b > 0:
        sel &= v >= lo
    if b < bins - 1:
        sel &= v < hi
    return sel


def worst_cell(table: pd.DataFrame, ratio: float, alpha: float, halves=None):
    """The (channel, regime, bin) row with the largest ratio among the cells whose excess over
    the floor is significant after a Bonferroni correction over all cells, or None. With
    ``halves`` (the same table on two disjoint sets of flights) a cell must also be above
    the floor by half the excess in each: a real effect replicates, a chance cell does not."""
    from scipy.stats import norm
    z = norm.ppf(1.0 - alpha / max(len(table), 1))
    t = table[(table.ratio > ratio) & (table.z > z)]
    if halves is not None:
        keys = ["channel", "regime", "bin"]
        for h in halves:
            ok = h[h.ratio > 1.0 + 0.5 * (ratio - 1.0)][keys]
            t = t.merge(ok, on=keys)
    if t.empty:
        return None
    return t.sort_values("ratio", ascending=False).iloc[0].to_dict()


def flight_losses(r: np.ndarray, flight_of: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(F, C) mean normalised squared residual of each flight's windows, per channel."""
    e = np.mean((r / sigma) ** 2, axis=1)
    ids = np.unique(flight_of)
    return np.stack([e[flight_of == f].mean(axis=0) for f in ids]) if len(ids) else np.zeros((0, e.shape[1]))


def channel_excess(r, flight_of, r_floor, floor_flight_of, sigma, channels, draws: int = 4999) -> pd.DataFrame:
    """Per channel: the flights' loss over the floor flights' (ratio) and the one-sided p-value
    of their mean being that far above the floor's by chance, from a permutation test of the
    flight labels (exact when there are at most ``draws`` ways to choose them, else ``draws``
    random ones). Flights, not windows, are the samples: windows of one flight share its
    manoeuvres and disagree with the floor together, so a window-level test takes one set of
    nominal flights' difference from another for a signal. Permutations, not a t: per-flight
    losses are skewed, and a t on 8 floor flights named 2 of 20 nominal flight sets."""
    from itertools import combinations
    from math import comb

    a, f = flight_losses(r, flight_of, sigma), flight_losses(r_floor, floor_flight_of, sigma)
    fm = np.maximum(f.mean(axis=0), 1e-12)
    pooled = np.concatenate([a, f])
    n, k = len(pooled), len(a)
    if comb(n, k) <= draws:
        picks = np.array(list(combinations(range(n), k)))
    else:
        rng = np.random.default_rng(0)
        picks = np.array([rng.choice(n, k, replace=False) for _ in range(draws)])
    observed = a.mean(axis=0)
    null = pooled[picks].mean(axis=1)                      # (permutations, C)
    # the observed labelling counts as one of the permutations (exact: it is among them)
    extra = 0 if len(picks) == comb(n, k) else 1
    p = ((null >= observed - 1e-12).sum(axis=0) + extra) / (len(picks) + extra)
    return pd.DataFrame({"channel": list(channels), "flights": k, "ratio": observed / fm, "p": p})


def unexplained_channels(held: pd.DataFrame, train: pd.DataFrame, ratio: float, alpha: float) -> list[str]:
    """Channels whose residual stays above the floor: on the held-out flights by more than
    ``ratio`` x and significantly (permutation p below alpha, Bonferroni over channels), and
    replicated on the training flights (above the floor, p below alpha)."""
    h = held[(held.ratio > ratio) & (held.p <= alpha / max(len(held), 1))]
    t = train[(train.ratio > 1.0) & (train.p <= alpha)]
    return [c for c in h.channel if c in set(t.channel)]


def unexplained_cell(table: pd.DataFrame, channels: list[str], ratio: float, alpha: float):
    """Where the unexplained channels disagree most: the worst significant regime cell of
    ``table`` among them, else the worst channel as a whole; None when no channel is left."""
    if not channels:
        return None
    cell = worst_cell(table[table.channel.isin(channels)], ratio, alpha)
    if cell is None:
        cell = table[(table.regime == "all") & table.channel.isin(channels)].sort_values("ratio").iloc[-1].to_dict()
    cell["channels"] = list(channels)
    return cell


def heatmap(table: pd.DataFrame, path, title: str) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    t = table[table.regime != "all"].copy()
    t["col"] = t.regime + ":" + t.bin.astype(str)
    grid = t.pivot_table(index="channel", columns="col", values="ratio", sort=False)
    grid = grid.reindex(index=list(dict.fromkeys(table.channel)))
    fig, ax = plt.subplots(figsize=(1.0 + 0.45 * grid.shape[1], 1.0 + 0.3 * grid.shape[0]))
    im = ax.imshow(np.log2(np.clip(grid.to_numpy(), 1 / 16, 16)), cmap="RdBu_r", vmin=-3, vmax=3, aspect="auto")
    ax.set_xticks(range(grid.shape[1]), grid.columns, rotation=90, fontsize=7)
    ax.set_yticks(range(grid.shape[0]), grid.index, fontsize=7)
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, label="log2(residual / noise floor)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)

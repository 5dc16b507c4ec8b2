"""``sdexp experiment=model_test``: do the learned d, g, h (and their linearisation) capture the
dynamics? The two tests of the paper's "Testing the Linearized Networks".

(a) Acceleration. The networks predict next-frame velocities from current ones; a network that
    only copied its input would still predict velocities well. So on the held-out episodes
    (``Dataset.split(data.validation_fraction, seed)``) the acceleration reconstructed from the
    prediction, (pred_next - current) / alpha, is compared with the measured one,
    (next - current) / alpha, per channel: R^2 = 1 - SS_res / SS_tot in ``acceleration_r2.csv``
    (``r2_no_change`` is the R^2 of predicting zero acceleration, the copying network's score),
    overlaid in ``acceleration.png``. Nets trained with ``model.horizon`` k > 1 (the controllers'
    recipe) are tested on their own targets: alpha = k control intervals, on the held-out rows
    whose k-frame target exists.

(b) Rollout. A test flight of ``rollout_seconds`` under random thrust holds like the training
    data (``data.hold_seconds``, U[-Tmax, Tmax] per rotor): the longest held-out episode if one
    is long enough, else (the usual case: data episodes end after ``data.episode_seconds`` or on
    leaving ``data.region``) a dedicated flight simulated with ``Simulator`` and read through
    the sensors only, with the configured noise and delay, seed ``seed + test_seed_offset``
    (a flight the simulator fails -- blow-up under the wild tumbling -- is retried with the next
    seed, up to ``flight_attempts``; the longest is kept and ``flight_seconds`` says its length).
    From the flight's first state and driven by its logged commands, three predictions:
      linearized   Eq. 5 relinearised every ``relinearize_every`` steps (5 = 20 Hz) at the current
                   *predicted* state and command: x_{k+1} = x_k + dt (f* + A (x_k - x*) + B (u_k - u*)),
                   open loop for the whole flight (the paper's "Jacobian Matrix Update");
      nonlinear    x_{k+1} = x_k + dt f(x_k, u_k), open loop (dt the control interval);
      horizon      both restarted from the true state every ``horizon_seconds``: short-term
                   accuracy, the median error over the windows against the time since the
                   restart (a diverged window counts as infinitely wrong), with a
                   constant-velocity extrapolation for scale.
    Errors over time in ``rollout.csv`` (s, e: RMS over channels in rad, e wrapped to (-pi, pi];
    p, p_dot: Euclidean norm; s_dot, e_dot: RMS), ``rollout_horizon.csv``, plot ``rollout.png``.

(c) Input Jacobian. The learned B = df/du against the simulator's, from finite pushes on each
    rotor at rest (``input_jacobian_check``): ``input_jacobian.csv``.

Training curves of the networks: ``training.csv`` and ``training.png``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from sdexp.model.dynamics import LearnedDynamics, state_sizes
from sdexp.model.specs import DECOMPOSED
from sdexp.model.identification import identify
from sdexp.model.training import design, design_rows, history_table, loss_plot
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


GROUPS = ("s", "e", "p")
VEL = {"s": "s_dot", "e": "e_dot", "p": "p_dot"}


def channel_names(sizes: dict) -> dict[str, list[str]]:
    axes = ["x", "y", "z"][: sizes["dim"]]
    e = ["e_x", "e_y", "e_z"] if sizes["n_e"] == 3 else ["theta"]
    return {"s": [f"s_{i + 1}" for i in range(sizes["n_s"])], "e": e, "p": [f"p_{a}" for a in axes]}


# ------------------------------------------------------------------------------ (a) acceleration

@torch.no_grad()
def acceleration_test(data, trained, val_idx: np.ndarray, alpha: float, horizon: int = 1, delay: int = 0,
                      frame: str = "world"):
    """Per-channel R^2 of the reconstructed acceleration on the given transitions (those whose
    ``horizon``-frame target exists, ``alpha`` apart); returns (table, {group: (true accel,
    predicted accel)}, the dataset rows they are of, sorted). With ``frame`` "heading" the nets
    are scored as they learned, the horizontal acceleration along and across the heading."""
    names = channel_names(state_sizes(data))
    rows, series = [], {}
    used = design_rows(data, val_idx, horizon, delay)
    for spec, group in zip(DECOMPOSED, GROUPS):
        if spec.name not in trained.nets:
            continue
        X, Y, base = design(data, spec, val_idx, horizon, delay, frame)
        net = trained.nets[spec.name]
        pred = np.concatenate([net(torch.from_numpy(X[i:i + 65536])).numpy() for i in range(0, len(X), 65536)])
        cur = X[:, base]
        a_true, a_pred = (Y - cur) / alpha, (pred - cur) / alpha
        series[group] = (a_true, a_pred)
        ss_tot = ((a_true - a_true.mean(0)) ** 2).sum(0)
        ss_res = ((a_pred - a_true) ** 2).sum(0)
        ss_zero = (a_true ** 2).sum(0)
        for j, name in enumerate(names[group]):
            rows.append({"group": group, "channel": name, "network": spec.name,
                         "r2": 1 - ss_res[j] / ss_tot[j], "r2_no_change": 1 - ss_zero[j] / ss_tot[j],
                         "mae_accel": float(np.abs(a_pred[:, j] - a_true[:, j]).mean()),
                         "std_accel": float(a_true[:, j].std()), "samples": len(X)})
    return pd.DataFrame(rows), series, used


def acceleration_plot(data, rows, series, table, dt: float, seconds: float, path: Path) -> None:
    """``rows``: the dataset rows of ``series`` (acceleration_test); ``seconds`` of the longest
    held-out episode, ``dt`` between rows."""
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    ep = data.arrays["episode"][rows]
    ids, counts = np.unique(ep, return_counts=True)
    longest = ids[np.argmax(counts)]
    sel = np.flatnonzero(ep == longest)
    sel = sel[np.argsort(data.arrays["t"][rows][sel])][: max(2, int(round(seconds / dt)))]
    t = data.arrays["t"][rows][sel]
    groups = list(series)
    ncol = 3
    fig, axes = plt.subplots(len(groups), ncol, figsize=(12, 2.6 * len(groups)), squeeze=False)
    for r, g in enumerate(groups):
        a_true, a_pred = series[g]
        tab = table[table["group"] == g].reset_index(drop=True)
        order = np.argsort(-tab["std_accel"].to_numpy())[:ncol]   # the liveliest channels
        for c in range(ncol):
            ax = axes[r, c]
            if c >= len(order):
                ax.axis("off")
                continue
            j = order[c]
            ax.plot(t, a_true[sel, j], color="k", lw=1.2, label="measured")
            ax.plot(t, a_pred[sel, j], color="tab:red", lw=1.0, ls="--", label="from predicted velocity")
            ax.set_title(f"{tab['channel'][j]}: accel., R^2 = {tab['r2'][j]:.3f}", fontsize=9)
            ax.grid(alpha=0.3)
            if r == len(groups) - 1:
                ax.set_xlabel("t (s)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Held-out episode: measured acceleration vs (predicted velocity - velocity) / alpha")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


# ------------------------------------------------------------------------------ (b) rollout

def _episode_from_data(data, val_idx, steps: int):
    """The longest held-out episode as (X (T, n), U (T-1, m)) if it has >= steps + 1 states."""
    a = data.arrays
    ep = a["episode"][val_idx]
    ids, counts = np.unique(ep, return_counts=True)
    if counts.max() < steps + 1:
        return None
    sel = val_idx[ep == ids[np.argmax(counts)]]
    sel = sel[np.argsort(a["t"][sel])][: steps + 1]
    X = np.concatenate([a[k][sel] for k in ("s", "s_dot", "e", "e_dot", "p", "p_dot")], axis=1).astype(np.float64)
    return X, a["u"][sel[:-1]].astype(np.float64)


def simulate_flight(cfg, seconds: float, seed: int, attempts: int = 5):
    """A test flight under random thrust holds drawn as the data were, read through the sensors only:
    (X (T+1, n) decomposed states, U (T, m) commands, seed used). A flight that fails is
    retried with the next seed; the longest one is kept."""
    from sdexp.log import Phase
    from sdexp.model.generate import commands, thrust_draw
    from sdexp.sim.drone import build_drone
    from sdexp.sensing import decompose
    from sdexp.sim.simulator import Simulator

    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    dt = float(cfg.sim.control_dt)
    steps = int(round(seconds / dt))
    best = None
    draw = thrust_draw(drone, cfg.data, cfg.sim, cfg.cache_dir)
    for attempt in range(attempts):
        sim = Simulator(drone, cfg.sim, cfg.noise, seed + attempt)
        cmds = commands(drone, cfg.data, draw, dt, np.random.default_rng(seed + attempt))
        xs = [decompose(sim.reset(), drone.layout).x]
        us = []
        for _ in Phase(f"test flight {attempt}", total=steps, unit="steps").iterate(range(steps)):
            u = next(cmds)
            r = sim.step(u)
            if not sim.alive:
                log.info(f"sdexp: test flight {attempt}: {sim.failure.reason} at {sim.failure.time:.2f} s, retrying")
                break
            us.append(u.copy())
            xs.append(decompose(r, drone.layout).x)
        if best is None or len(us) > len(best[1]):
            best = (np.array(xs), np.array(us).reshape(len(us), drone.num_rotors), seed + attempt)
        if len(us) == steps:
            break
    return best


def input_jacobian_check(cfg, dyn: LearnedDynamics, steps: tuple[int, ...] = (1, 10), du: float = 1.0) -> pd.DataFrame:
    """The learned B (df/du) against the simulator's, at rest under equal hover-sized thrusts:
    each rotor is pushed ``du`` N above the others for k control steps in the noise-free (and
    delay-free) simulator and the mean velocity change per N is compared, per velocity block,
    with the learned dB/du. This is what the LQR relies on. ``rel_error`` = |B_learned -
    B_sim| / |B_sim| (Frobenius), ``sign_agreement`` = fraction of the entries above 10% of the
    block's largest whose signs agree. Over one step the response is local (the thrust has not
    reached the rest of a soft body yet); over ten, rigid-like."""
    from sdexp.sim.drone import build_drone
    from sdexp.sim.simulator import Simulator

    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    quiet = replace(cfg.noise, enabled=False)
    u0 = np.full(dyn.m, float(cfg.drone.mass) * float(cfg.sim.gravity) / dyn.m)
    x0 = Simulator(drone, cfg.sim, quiet).state(noisy=False).x
    _, _, B_learned = dyn.linearize(x0, u0)
    dt = float(cfg.sim.control_dt)

    def mean_acceleration(u, k):
        sim = Simulator(drone, cfg.sim, quiet)
        for _ in range(k):
            sim.step(u)
        return (sim.state(noisy=False).x - x0) / (k * dt)

    rows = []
    for k in steps:
        base = mean_acceleration(u0, k)
        B_sim = np.stack([mean_acceleration(u0 + du * np.eye(dyn.m)[i], k) - base for i in range(dyn.m)], 1) / du
        for vel in ("s_dot", "e_dot", "p_dot"):
            sl = dyn.slices[vel]
            bs, bl = B_sim[sl], B_learned[sl]
            if bs.size == 0:
                continue
            big = np.abs(bs) > 0.1 * np.abs(bs).max()
            rows.append({"steps": k, "block": vel, "rel_error": float(np.linalg.norm(bl - bs) / np.linalg.norm(bs)),
                         "sign_agreement": float(np.mean(np.sign(bl[big]) == np.sign(bs[big]))),
                         "norm_sim": float(np.linalg.norm(bs)), "norm_learned": float(np.linalg.norm(bl))})
    return pd.DataFrame(rows)


def rollout(dyn: LearnedDynamics, x0: np.ndarray, U: np.ndarray, every: int, linear: bool = True,
            X_true: np.ndarray | None = None, restart: int | None = None):
    """Predicted states (T+1, n) from x0 under commands U (T, m). linear: Eq. 5 relinearised
    every ``every`` steps at the predicted state; else the explicit nonlinear step. With
    ``restart`` and ``X_true`` the prediction restarts from the truth every ``restart`` steps.
    A prediction that leaves all sense (non-finite or > 1e6) is NaN from there on.
    Returns (states, seconds per linearisation call)."""
    T = len(U)
    X = np.full((T + 1, len(x0)), np.nan)
    X[0] = x = np.asarray(x0, dtype=np.float64)
    lin_times = []
    f0 = A = B = xs = us = None
    for k in range(T):
        restarting = bool(restart) and k % restart == 0
        if restarting:   # X[k] keeps the previous window's prediction
            x = X_true[k].astype(np.float64)
        elif np.isnan(x[0]):
            continue     # diverged in this window: NaN until the next restart
        if linear:
            if k % every == 0 or restarting:
                t0 = time.perf_counter()
                f0, A, B = dyn.linearize(x, U[k])
                lin_times.append(time.perf_counter() - t0)
                xs, us = x.copy(), U[k].copy()
            x = x + dyn.dt * (f0 + A @ (x - xs) + B @ (U[k] - us))
        else:
            x = x + dyn.dt * dyn.f(x, U[k])
        if not np.all(np.isfinite(x)) or np.abs(x).max() > 1e6:
            if not restart:
                break
            x = np.full_like(x, np.nan)
            continue
        X[k + 1] = x
    return X, lin_times


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def state_errors(dyn: LearnedDynamics, X_hat: np.ndarray, X_true: np.ndarray) -> dict[str, np.ndarray]:
    """Per-time error of each block: s, e, s_dot, e_dot RMS over channels (e wrapped), p, p_dot
    Euclidean norm."""
    out = {}
    for k, sl in dyn.slices.items():
        if k == "u" or sl.stop == sl.start:
            continue
        d = X_hat[:, sl] - X_true[:, sl]
        if k == "e":
            d = _wrap(d)
        out[k] = np.linalg.norm(d, axis=1) if k in ("p", "p_dot") else np.sqrt(np.mean(d ** 2, axis=1))
    return out


def rollout_plot(t, X_true, preds: dict, errs: dict, dyn, names, path: Path) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    sl = dyn.slices
    show = [("p", 1, f"{names['p'][1]} (m)"), ("p", 0, f"{names['p'][0]} (m)"),
            ("e", 0, f"{names['e'][0]} (rad)")]
    if dyn.n_s:
        show.append(("s", 0, f"{names['s'][0]} (rad)"))
    fig, axes = plt.subplots(2, 3, figsize=(14, 7))
    for ax, (blk, j, label) in zip(axes.flat[: len(show)], show):
        i = sl[blk].start + j
        ax.plot(t, X_true[:, i], color="k", lw=1.2, label="ground truth")
        for (name, X), c in zip(preds.items(), ("tab:red", "tab:blue")):
            y = _wrap(X[:, i]) if blk == "e" else X[:, i]
            ax.plot(t, y, color=c, lw=0.9, ls="--", label=name)
        lo, hi = np.nanmin(X_true[:, i]), np.nanmax(X_true[:, i])
        pad = 0.3 * (hi - lo) + 1e-3
        ax.set_ylim(lo - pad, hi + pad)   # a diverging prediction leaves the frame, not the truth
        ax.set_xlim(0, t[-1])
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("t (s)")
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=8)
    for ax in axes.flat[len(show):5]:
        ax.axis("off")
    ax = axes.flat[5]
    for (name, e), ls in zip(errs.items(), ("-", "--")):
        for (blk, v), c in zip(e.items(), plt.rcParams["axes.prop_cycle"].by_key()["color"]):
            if blk in ("s", "e", "p"):
                ax.semilogy(t, v, color=c, ls=ls, lw=0.9, label=f"{blk} ({name})")
    ax.set_xlim(0, t[-1])
    ax.set_title("error (s, e: RMS rad; p: m); ends where a prediction diverges", fontsize=9)
    ax.set_xlabel("t (s)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    fig.suptitle("Open-loop prediction of a test flight from its logged commands")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


# ------------------------------------------------------------------------------ runner

def speed_table(data, trained) -> pd.DataFrame:
    """The issue's speed figures: how fast the dataset was generated (recorded when it was,
    so a cached run still reports it) and how long each network trained."""
    m = data.meta
    rows = [{"item": "dataset", "samples": m.get("samples"), "workers": m.get("workers"),
             "seconds": m.get("wall_seconds"), "samples_per_second": m.get("samples_per_second"),
             "cached": bool(m.get("cached"))}]
    rows += [{"item": f"train {n}", "samples": None, "workers": None, "seconds": float(trained.seconds[n]),
              "epochs": len(h), "cached": bool(trained.cached)} for n, h in trained.history.items()]
    return pd.DataFrame(rows)


def run(run: Run) -> dict:
    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    dt = float(cfg.sim.control_dt)                  # between rows, commands and rollout steps
    horizon = int(cfg.model.horizon)
    alpha = dt * horizon                            # between a net's input and its target
    data, trained, dyn = identify(cfg)
    run.table(history_table(trained), "training")
    loss_plot(trained, out_dir / "training.png", f"{cfg.drone.name}: d, g, h training")
    run.table(speed_table(data, trained), "bench_model")
    metrics = _training_metrics(trained)

    # (a) acceleration on held-out episodes
    _, val_idx = data.split(float(cfg.data.validation_fraction), int(cfg.seed))
    table, series, rows = acceleration_test(data, trained, val_idx, alpha, horizon, dyn.delay, str(cfg.model.frame))
    run.table(table, "acceleration_r2")
    acceleration_plot(data, rows, series, table, dt, float(p.plot_seconds),
                      out_dir / "acceleration.png")
    for g, grp in table.groupby("group", sort=False):
        metrics[f"r2_mean_{VEL[g]}"] = float(grp["r2"].mean())
    metrics["r2_mean"] = float(table["r2"].mean())
    metrics["r2_no_change_mean"] = float(table["r2_no_change"].mean())
    log.info(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))

    # (c) the learned input Jacobian against the simulator's (what the LQR relies on)
    jac = input_jacobian_check(cfg, dyn)
    run.table(jac, "input_jacobian")
    for r in jac.itertuples():
        metrics[f"input_jacobian_{r.block}_{r.steps}step_rel_error"] = r.rel_error
        metrics[f"input_jacobian_{r.block}_{r.steps}step_sign_agreement"] = r.sign_agreement
    log.info(jac.to_string(index=False, float_format=lambda v: f"{v:.3g}"))

    # (b) rollout of the linearized model against a test flight
    X_true, U, metrics["flight_source"] = _test_flight(cfg, p, data, val_idx, dt)
    T = len(U)
    t = dt * np.arange(T + 1)
    if dyn.delay:   # the model steps on the commands acting (the flight starts with idle rotors)
        U = np.concatenate([np.zeros((min(dyn.delay, T), U.shape[1])), U[:T - dyn.delay]])
    metrics["flight_seconds"] = float(T * dt)
    every = int(p.relinearize_every)
    X_lin, lin_times = rollout(dyn, X_true[0], U, every, linear=True)
    X_nl, _ = rollout(dyn, X_true[0], U, every, linear=False)
    restart = max(1, int(round(float(p.horizon_seconds) / dt)))
    X_hz, _ = rollout(dyn, X_true[0], U, every, linear=True, X_true=X_true, restart=restart)
    X_hz_nl, _ = rollout(dyn, X_true[0], U, every, linear=False, X_true=X_true, restart=restart)
    errs = {"linearized": state_errors(dyn, X_lin, X_true), "nonlinear": state_errors(dyn, X_nl, X_true)}
    cols = {"t": t}
    for mode, e in errs.items():
        cols.update({f"{mode}_{k}": v for k, v in e.items()})
    run.table(pd.DataFrame(cols), "rollout")
    rollout_plot(t, X_true, {"linearized (20 Hz)": X_lin, "nonlinear": X_nl}, errs, dyn,
                 channel_names(state_sizes(data)), out_dir / "rollout.png")

    hz = {"linearized": state_errors(dyn, X_hz, X_true), "nonlinear": state_errors(dyn, X_hz_nl, X_true),
          "constant_velocity": state_errors(dyn, _constant_velocity(dyn, X_true, restart, dt), X_true)}
    horizon = _horizon_table(hz, T, restart, dt)
    run.table(horizon, "rollout_horizon")
    metrics.update(_rollout_metrics(dyn, errs, hz, horizon, X_hz, X_hz_nl, X_true, restart, dt))
    if lin_times:
        metrics.update(jacobians_ms_mean=1e3 * float(np.mean(lin_times)), jacobians_ms_median=1e3 * float(np.median(lin_times)))
    return metrics


def _training_metrics(trained) -> dict:
    """Each net's training time, its kept validation L1 and epoch."""
    metrics: dict = {"nets_cached": trained.cached, "train_wall_seconds": float(trained.wall_seconds)}
    for n, h in trained.history.items():
        metrics[f"train_seconds_{n}"] = float(trained.seconds[n])
        metrics[f"val_l1_{n}"] = float(h["val_l1"][h["selected"]].iloc[0] if h["selected"].any() else h["val_l1"].iloc[-1])
        metrics[f"epoch_kept_{n}"] = int(h["epoch"][h["selected"]].iloc[0]) if h["selected"].any() else int(h["epoch"].iloc[-1])
    return metrics


def _test_flight(cfg, p, data, val_idx, dt: float) -> tuple[np.ndarray, np.ndarray, str]:
    """(X_true, U, where it came from): a held-out episode long enough, else a simulated flight."""
    steps = int(round(float(p.rollout_seconds) / dt))
    found = _episode_from_data(data, val_idx, steps)
    if found is not None:
        return *found, "held-out episode"
    X_true, U, used_seed = simulate_flight(cfg, float(p.rollout_seconds), int(cfg.seed) + int(p.test_seed_offset),
                                           int(p.flight_attempts))
    return X_true, U, f"simulated, seed {used_seed}"


def _constant_velocity(dyn, X_true: np.ndarray, restart: int, dt: float) -> np.ndarray:
    """The baseline prediction: each window restarted from the truth, then constant rates."""
    T = len(X_true) - 1
    const_vel = X_true.copy()
    for k0 in range(0, T, restart):
        k1 = min(k0 + restart, T)
        tau = dt * np.arange(k1 - k0 + 1)[:, None]
        x0 = X_true[k0]
        seg = np.repeat(x0[None], k1 - k0 + 1, axis=0)
        for blk, vel in VEL.items():
            seg[:, dyn.slices[blk]] = x0[dyn.slices[blk]] + tau * x0[dyn.slices[vel]]
        const_vel[k0 + 1:k1 + 1] = seg[1:]   # index k0 keeps the previous window's prediction
    return const_vel


def _horizon_table(hz: dict, T: int, restart: int, dt: float) -> pd.DataFrame:
    """Error against time since the restart from the truth, median over the windows."""
    rows = []
    for j in range(1, restart + 1):
        # predictions j steps after a restart: the state at index k0 + j
        idx = np.arange(j, T + 1, restart)
        row = {"tau": j * dt}
        for mode, e in hz.items():
            for blk, v in e.items():
                w = v[idx]
                w = np.where(np.isfinite(w), w, np.inf)   # a diverged window counts as the worst
                row[f"{mode}_{blk}"] = float(np.median(w)) if len(idx) else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def _rollout_metrics(dyn, errs: dict, hz: dict, horizon: pd.DataFrame, X_hz, X_hz_nl, X_true,
                     restart: int, dt: float) -> dict:
    """The rollouts' errors at 1, 10 and 60 s, where they diverge, the restarted windows' errors
    at the horizon and share diverged, and the test flight's own spread and distance."""
    metrics: dict = {}
    T = len(X_true) - 1
    for mode, e in errs.items():
        for sec in (1.0, 10.0, 60.0):
            k = int(round(sec / dt))
            if k <= T:
                for blk in ("s", "e", "p", "p_dot"):
                    if blk in e:
                        v = e[blk][k]
                        metrics[f"rollout_{mode}_{blk}_err_{int(sec)}s"] = float(v) if np.isfinite(v) else None
        finite = np.flatnonzero(~np.isfinite(e["p"]))
        metrics[f"rollout_{mode}_diverged_at"] = float(finite[0] * dt) if len(finite) else None
    last = horizon.iloc[-1]
    for blk in ("s", "e", "p", "p_dot"):
        for mode in hz:
            if f"{mode}_{blk}" in last:
                v = float(last[f"{mode}_{blk}"])
                metrics[f"horizon_{blk}_err_{mode}"] = v if np.isfinite(v) else None
    ends = np.arange(restart, T + 1, restart)
    for mode, X in (("linearized", X_hz), ("nonlinear", X_hz_nl)):
        metrics[f"horizon_diverged_fraction_{mode}"] = float(np.mean(~np.isfinite(X[ends, 0]))) if len(ends) else None
    metrics["horizon_seconds"] = restart * dt
    spread = state_errors(dyn, np.broadcast_to(np.nanmean(X_true, 0), X_true.shape), X_true)
    for blk in ("s", "e", "p_dot"):
        if blk in spread:
            metrics[f"flight_spread_{blk}"] = float(np.sqrt(np.mean(spread[blk] ** 2)))
    metrics["flight_distance_m"] = float(np.linalg.norm(X_true[-1, dyn.slices["p"]] - X_true[0, dyn.slices["p"]]))
    return metrics



"""Training the d, g, h networks of Eq. 4 (supplement F), and the undecomposed ablation network
(what each reads and predicts: sdexp.model.specs).

Each network is a :class:`~sdexp.model.networks.ResidualMLP` trained separately on the same
transitions: Adam (``model.lr``), the learning rate multiplied by ``model.lr_decay`` every
``model.lr_step`` epochs (StepLR), ``model.batch_size``, ``model.epochs``, on the episode split
``Dataset.split(data.validation_fraction, seed)``; the last incomplete batch of each shuffled
epoch is dropped. With ``model.threads >= 2`` the networks train at the same time, each in its
own process with one torch thread (faster than one network after another on two threads, and
robust to a busy machine; see ``_train_parallel``); with 1, one after another in this process.
A network's result depends only on its data, the config and its seed, not on which way it ran.

The loss (``model.loss``: l1 or l2) is taken on the network's standardised output, i.e. on
``(pred_next - target_next) / std(target_next - current)`` per channel, averaged over channels:
the L1 loss of the paper with every channel weighted by the spread of its one-frame velocity
change, so a fast channel does not drown a slow one. ``val_l1`` in the history is this
normalised L1 on the held-out episodes whatever ``model.loss`` is: 0 is a perfect prediction,
predicting "no change" scores mean|change| / std(change) (about 0.8 for a Gaussian change, as
little as 0.1 for the spiky Euler rates near the gimbal lock). ``val_rel_l1`` is free of that
dependence on the tails: per channel the validation mean absolute error over that of predicting
"no change", averaged over channels (1 = no better than copying the current velocity, 0 =
perfect); ``val_rel_l1_channels`` holds it per channel. The decomposition ablation compares it.

The network returned is the one of the epoch with the lowest validation loss (``model.keep_best``,
default True while ModelConfig lacks the key; False returns the last epoch, the paper's plain
recipe). On the default flower data the paper's 50 epochs overfit all three networks after
5-20 epochs (validation loss rising again); the best epoch's networks reconstruct the held-out
accelerations better (R^2 of s 0.24 vs 0.07) and linearise to a far less unstable A. The
history marks the chosen epoch (``selected``). The held-out episodes thus also pick the epoch.

Trained networks are cached under ``cache_dir`` keyed by :func:`sdexp.cache.key_of` over the
dataset's content hash, the model config's key fields (not ``threads``), the seed, the network
specs and FORMAT_VERSION, and
written atomically; a cached file whose stored version or key does not match, or that cannot be
read, is retrained and replaced (with a message), never used.
"""
from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np
import pandas as pd
import torch

from sdexp.cache import atomic_write, build_lock, config_key, key_of
from sdexp.errors import UserError
from sdexp.parallel import run_spawned
from sdexp.model.networks import EnsembleMLP, ResidualMLP
from sdexp.model.heading import TILT, YAW, applies, turn
from sdexp.model.specs import DECOMPOSED, NetSpec

log = logging.getLogger(__name__)

FORMAT_VERSION = 6   # 2: keep_best, "selected"; 3: val_rel_l1; 4: val_rel_l1_channels; 5: keep_best in the key;
                     # 6: the model config's key fields (sdexp.cache.config_key)


@dataclass
class TrainedNets:
    nets: dict[str, ResidualMLP]
    history: dict[str, pd.DataFrame]   # per network: epoch, lr, train_loss, val_loss, val_l1
    seconds: dict[str, float]          # training wall time per network (as trained, also when loaded)
    key: str
    cached: bool = False               # True when loaded from the cache
    specs: tuple[NetSpec, ...] = DECOMPOSED
    skipped: list[str] = field(default_factory=list)  # specs with an empty target (no sensors)
    wall_seconds: float = 0.0          # training wall time of the whole set (networks may overlap)


def member_seed(seed: int, k: int) -> int:
    """The training seed of ensemble member ``k`` (``model.ensemble``): member 0 trains from the
    run's seed (its nets are those of ensemble 1, from the same cache), the others from seeds
    drawn from (seed, k), far from any seed a user runs."""
    return int(seed) if k == 0 else int(np.random.SeedSequence([int(seed), int(k)]).generate_state(1)[0]) + 2 ** 32


def ensemble(members: Sequence[TrainedNets]) -> TrainedNets:
    """One TrainedNets whose nets are the members' means (EnsembleMLP); the curves are member 0's,
    the times the members' sums (they trained one after the other)."""
    if len(members) == 1:
        return members[0]
    first = members[0]
    return TrainedNets({n: EnsembleMLP([m.nets[n] for m in members]) for n in first.nets}, first.history,
                       {n: sum(m.seconds[n] for m in members) for n in first.seconds},
                       key_of("nets", FORMAT_VERSION, [m.key for m in members]), all(m.cached for m in members),
                       first.specs, first.skipped, sum(m.wall_seconds for m in members))


# ------------------------------------------------------------------------------ data

def _arrays(data) -> dict[str, np.ndarray]:
    return data.arrays if hasattr(data, "arrays") else data


def horizon_rows(data, horizon: int, delay: int = 0) -> np.ndarray:
    """Rows i whose target ``horizon`` frames ahead exists: rows i .. i + horizon - 1 are
    consecutive frames of one episode under one acting command (a constant-thrust hold); with a
    command ``delay``, row i also needs the command sent ``delay`` frames before it, in its episode."""
    a = _arrays(data)
    n = len(a["u"])
    i = np.arange(max(n - horizon + 1, 0))
    if horizon == 1 and delay == 0:
        return i
    ep = np.asarray(a["episode"])
    u = acting_commands(a, delay)
    ok = np.ones(len(i), bool)
    # an episode's rows are consecutive frames (generate.py)
    if delay:
        ok &= (i >= delay) & (ep[np.maximum(i - delay, 0)] == ep[i])
    for j in range(1, horizon):
        ok &= (ep[i + j] == ep[i]) & np.all(u[i + j] == u[i], axis=1)
    return i[ok]


def acting_commands(data, delay: int) -> np.ndarray:
    """The command acting at each row: the one sent ``delay`` frames earlier (``model.command_delay``;
    rows without one, at an episode's start, get row 0's and are dropped by ``horizon_rows``)."""
    u = np.asarray(_arrays(data)["u"])
    return u if delay == 0 else np.concatenate([np.repeat(u[:1], delay, axis=0), u[:-delay]])[:len(u)]


def design_rows(data, idx: np.ndarray | None = None, horizon: int = 1, delay: int = 0) -> np.ndarray:
    """The rows (of ``idx``, or all; sorted) that ``design`` keeps: those with a ``horizon``-frame
    target and, with a command ``delay``, a command that acts on them."""
    rows = horizon_rows(_arrays(data), horizon, delay)
    return rows if idx is None else np.intersect1d(rows, idx)


def design(data, spec: NetSpec, idx: np.ndarray | None = None, horizon: int = 1, delay: int = 0,
           frame: str = "world") -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(inputs (N, n_in), targets (N, n_out), base) for one network; base[j] is the input column
    holding the current value of output j. ``horizon`` k > 1: the target is the velocity k
    frames ahead under the same command (``model.horizon``), rows without one are dropped.
    ``delay``: the input u is the command sent that many frames earlier (``model.command_delay``).
    ``frame``: "heading" gives a net that reads e its tilt alone and p_dot and its target in the
    heading frame of the input's row (sdexp.model.heading)."""
    a = _arrays(data)
    missing = [k for k in (*spec.inputs, spec.target) if k not in a]
    if missing:
        raise UserError(f"the dataset has no {missing} arrays, needed by network {spec.name!r}")
    rows = design_rows(a, idx, horizon, delay)
    part = lambda arr, at: np.asarray(arr, dtype=np.float32).reshape(len(arr), -1)[at]
    cols = {k: part(acting_commands(a, delay) if k == "u" else a[k], rows) for k in spec.inputs}
    Y = part(a[spec.target], rows + horizon - 1)
    if "e" in cols and applies(frame, cols["e"].shape[1]):
        yaw = cols["e"][:, YAW]
        cols["e"] = cols["e"][:, list(TILT)]
        if "p_dot" in cols:
            cols["p_dot"] = turn(cols["p_dot"], yaw, -1.0)
        if spec.target == "p_dot_next":
            Y = turn(Y, yaw, -1.0)
    if spec.current not in cols or cols[spec.current].shape[1] != Y.shape[1]:
        raise UserError(f"network {spec.name!r}: {spec.current} must be an input as wide as {spec.target}")
    offset = sum(cols[k].shape[1] for k in spec.inputs[:spec.inputs.index(spec.current)])
    return np.concatenate([cols[k] for k in spec.inputs], axis=1), Y, list(range(offset, offset + Y.shape[1]))


def dataset_key(data, keys: Sequence[str]) -> str:
    """Content hash of the arrays a training run reads (exact: any changed sample is a miss)."""
    a = _arrays(data)
    h = hashlib.sha256()
    for k in sorted(set(keys) | {"episode"}):
        if k in a:
            arr = np.ascontiguousarray(a[k])
            h.update(f"{k}:{arr.dtype}:{arr.shape};".encode())
            h.update(arr.tobytes())
    return h.hexdigest()[:24]


def split_indices(data, validation_fraction: float, seed: int, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
    train, val = data.split(validation_fraction, seed)
    train, val = np.asarray(train), np.asarray(val)
    if len(val) == 0:
        raise UserError(f"the validation split is empty: data.validation_fraction = {validation_fraction} "
                        f"holds out no whole episode of {len(data)} transitions; raise data.samples or the fraction")
    if len(train) < batch_size:
        raise UserError(f"the training split has {len(train)} transitions, fewer than model.batch_size = "
                        f"{batch_size}: raise data.samples or lower model.batch_size")
    return train, val


# ------------------------------------------------------------------------------ training

def _loss_fn(kind: str):
    if kind == "l1":
        return lambda r, t: (r - t).abs().mean()
    if kind == "l2":
        return lambda r, t: ((r - t) ** 2).mean()
    raise UserError(f"model.loss = {kind!r} is unknown: choose l1 or l2")


def _adam(net, lr: float) -> torch.optim.Adam:
    """Adam; the fused CPU kernel where this torch has it (measured 10-25% faster per epoch
    here on 2 threads than the default foreach one), the same algorithm either way."""
    try:
        return torch.optim.Adam(net.parameters(), lr=lr, fused=True)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(net.parameters(), lr=lr)


@torch.no_grad()
def _evaluate(net: ResidualMLP, X: torch.Tensor, T: torch.Tensor, loss, chunk: int = 65536
              ) -> tuple[float, float, np.ndarray]:
    """(configured loss, normalised L1, per-channel mean absolute error in the target's units)
    of the raw outputs against standardised targets T."""
    tot_loss, tot_l1 = 0.0, 0.0
    abs_err = torch.zeros(T.shape[1], dtype=torch.float64)
    for i in range(0, len(X), chunk):
        r = net.raw_output(X[i:i + chunk])
        n = len(r)
        tot_loss += float(loss(r, T[i:i + chunk])) * n
        d = (r - T[i:i + chunk]).abs()
        tot_l1 += float(d.mean()) * n
        abs_err += d.sum(0).double()
    mae = (abs_err / len(X)).numpy() * net.out_std.double().numpy()
    return tot_loss / len(X), tot_l1 / len(X), mae


def train_network(X_tr: np.ndarray, Y_tr: np.ndarray, X_va: np.ndarray, Y_va: np.ndarray, base: list[int],
                  model_cfg, seed: int, name: str = "net", prior=None, progress: bool = True,
                  report: Callable[[int], None] | None = None, threads: int | None = None
                  ) -> tuple[ResidualMLP, pd.DataFrame, float]:
    """Train one ResidualMLP (``prior``: its fixed affine map, ``prior_maps``, or None); returns
    (net in eval mode, per-epoch history, wall seconds).
    ``report({"net", "epoch", "train", "val"})`` is called after every epoch with its losses
    (progress from a worker process); ``threads`` overrides ``model.threads``."""
    from sdexp.log import Phase

    torch.set_num_threads(int(threads or model_cfg.threads))
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    bs, epochs = int(model_cfg.batch_size), int(model_cfg.epochs)
    if len(X_tr) < bs:
        raise UserError(f"network {name!r}: {len(X_tr)} training transitions, fewer than model.batch_size = {bs}")
    X_tr, Y_tr = torch.from_numpy(np.ascontiguousarray(X_tr)), torch.from_numpy(np.ascontiguousarray(Y_tr))
    X_va, Y_va = torch.from_numpy(np.ascontiguousarray(X_va)), torch.from_numpy(np.ascontiguousarray(Y_va))
    hidden = 0 if name in model_cfg.linear else int(model_cfg.hidden)   # 0: a linear net
    net = ResidualMLP(X_tr.shape[1], Y_tr.shape[1], hidden, int(model_cfg.blocks), base, prior=prior is not None)
    if prior is not None:
        net.set_prior(*prior)
    net.fit_scaling(X_tr, Y_tr)
    with torch.no_grad():  # standardised targets once, not per batch
        T_tr, T_va = net.target_raw(X_tr, Y_tr), net.target_raw(X_va, Y_va)
        copy_mae = (Y_va - net.current(X_va)).abs().double().mean(0).numpy()   # "no change" error
        copy_mae = np.where(copy_mae > 1e-12, copy_mae, 1e-12)
    opt = _adam(net, float(model_cfg.lr))
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=int(model_cfg.lr_step), gamma=float(model_cfg.lr_decay))
    loss = _loss_fn(str(model_cfg.loss))
    rows = []
    keep_best = bool(model_cfg.keep_best)
    best_loss, best_state, best_epoch = float("inf"), None, epochs
    t0 = time.perf_counter()
    # a worker's progress goes through ``report`` to its parent's phase
    # (an error closes the phase with a line that says it stopped)
    with Phase(f"training net {name}", total=epochs, unit="epochs", enabled=progress and report is None) as bar:
        for epoch in range(1, epochs + 1):
            train_loss = _epoch(net, opt, loss, X_tr, T_tr, bs, gen)
            lr = opt.param_groups[0]["lr"]
            sched.step()
            net.eval()
            val_loss, val_l1, val_mae = _evaluate(net, X_va, T_va, loss)
            if not np.isfinite(train_loss):
                raise RuntimeError(f"network {name!r}: the training loss is {train_loss} at epoch {epoch}")
            if keep_best and val_loss < best_loss:
                best_loss, best_epoch = val_loss, epoch
                best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            rows.append({"epoch": epoch, "lr": lr, "train_loss": train_loss, "val_loss": val_loss,
                         "val_l1": val_l1, "val_rel_l1": float(np.mean(val_mae / copy_mae)),
                         "seconds": time.perf_counter() - t0,
                         "val_rel_l1_channels": [float(v) for v in val_mae / copy_mae]})
            bar.set_postfix(train=f"{train_loss:.4f}", val=f"{val_loss:.4f}")
            bar.update()
            if report is not None:
                report({"net": name, "epoch": epoch, "train": train_loss, "val": val_loss})
    seconds = time.perf_counter() - t0
    if best_state is not None:
        net.load_state_dict(best_state)
    history = pd.DataFrame(rows)
    history["selected"] = history["epoch"] == best_epoch
    return net.eval(), history, seconds


def _epoch(net, opt, loss, X_tr, T_tr, bs: int, gen) -> float:
    """One pass over the training set in shuffled full batches (the remainder dropped): the
    mean batch loss."""
    net.train()
    n_batches = len(X_tr) // bs
    perm = torch.randperm(len(X_tr), generator=gen)[: n_batches * bs]
    Xp, Tp = X_tr[perm], T_tr[perm]
    total = torch.zeros(())
    for b in range(n_batches):
        sl = slice(b * bs, (b + 1) * bs)
        batch_loss = loss(net.raw_output(Xp[sl]), Tp[sl])
        opt.zero_grad(set_to_none=True)
        batch_loss.backward()
        opt.step()
        total += batch_loss.detach()
    return float(total) / n_batches


# ------------------------------------------------------------------------------ cache

def models_key(data, model_cfg, seed: int, validation_fraction: float, specs: Sequence[NetSpec],
               priors: dict | None = None) -> str:
    """``model_cfg``: a sdexp.config.ModelConfig; ``priors``: train_models'."""
    model = {**config_key(model_cfg), "linear": sorted(model_cfg.linear)}   # which nets, in any order
    keys = {k for s in specs for k in (*s.inputs, s.target)}
    if int(model_cfg.horizon) > 1 or int(model_cfg.command_delay) > 0:
        keys |= {"u"}            # the rows design() keeps depend on it
    payload = {
        "data": dataset_key(data, sorted(keys)),
        "model": model,
        "seed": int(seed),
        "validation_fraction": float(validation_fraction),
        "specs": [asdict(s) for s in specs],
    }
    if priors:   # keyed only with one: the nets without are the ones cached before priors existed
        payload["priors"] = {k: [np.asarray(a, dtype=float).round(12).tolist() for a in v] for k, v in sorted(priors.items())}
    return key_of("nets", FORMAT_VERSION, payload)


def _save(path: Path, key: str, result: TrainedNets) -> None:
    blob = {
        "version": FORMAT_VERSION, "key": key,
        "nets": {n: {"spec": net.spec(), "state": net.state_dict()} for n, net in result.nets.items()},
        "history": {n: h.to_dict(orient="list") for n, h in result.history.items()},
        "seconds": dict(result.seconds),
        "skipped": list(result.skipped),
        "wall_seconds": float(result.wall_seconds),
    }
    atomic_write(path, lambda tmp: torch.save(blob, tmp))


def _load(path: Path, key: str, specs, quiet: bool = False) -> TrainedNets | None:
    say = (lambda msg: None) if quiet else log.warning
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated by hand, another torch's format, ...
        say(f"sdexp: cache entry {path.name} is unreadable ({type(err).__name__}), retraining")
        return None
    if not isinstance(blob, dict) or blob.get("version") != FORMAT_VERSION or blob.get("key") != key:
        say(f"sdexp: cache entry {path.name} is from another format version, retraining")
        return None
    nets = {n: ResidualMLP.from_saved(v["spec"], v["state"]) for n, v in blob["nets"].items()}
    history = {n: pd.DataFrame(h) for n, h in blob["history"].items()}
    return TrainedNets(nets, history, dict(blob["seconds"]), key, True, tuple(specs), list(blob.get("skipped", [])),
                       float(blob.get("wall_seconds", 0.0)))


def train_models(data, model_cfg, seed: int, cache_dir: str | Path | None, validation_fraction: float,
                 specs: Sequence[NetSpec] = DECOMPOSED, progress: bool = True, priors: dict | None = None) -> TrainedNets:
    """Train (or load from the cache) one network per spec on the episode split of ``data``.

    A spec whose target has no channels (a drone without peripheral sensors has an empty s, so
    no d) is skipped and listed in ``skipped``: its block of f is empty. ``priors`` (model.prior):
    target -> (per-newton acceleration of the command (n_out, m), constant acceleration (n_out,)),
    the rigid body's response at level; a spec with one adds it over ``alpha`` to the current
    velocity and learns the rest (``prior_maps``)."""
    specs = tuple(specs)
    key = models_key(data, model_cfg, seed, validation_fraction, specs, priors)
    path = Path(cache_dir).expanduser() / f"{key}.pt" if cache_dir is not None else None
    if path is not None and path.exists():
        loaded = _load(path, key, specs)
        if loaded is not None:
            return loaded
    if path is None:
        return _train_models(data, model_cfg, seed, None, validation_fraction, specs, key, progress, priors)
    with build_lock(path):   # concurrent jobs that need these nets: one trains, the others wait
        if path.exists():
            loaded = _load(path, key, specs, quiet=True)
            if loaded is not None:
                return loaded
        return _train_models(data, model_cfg, seed, path, validation_fraction, specs, key, progress, priors)


def prior_maps(spec: NetSpec, priors: dict | None, n_in: int, m: int, alpha: float):
    """The affine map (W (n_out, n_in), b (n_out,)) of ``spec``'s inputs that ``priors`` give its
    velocity change over ``alpha`` (the command is the inputs' last ``m`` columns), or None."""
    if not priors or spec.target not in priors:
        return None
    per_newton, constant = (np.asarray(a, dtype=float) for a in priors[spec.target])
    if spec.inputs[-1] != "u":
        raise ValueError(f"network {spec.name!r}: a prior needs the command u as its last input")
    W = np.zeros((per_newton.shape[0], n_in))
    W[:, n_in - m:] = alpha * per_newton
    return W, alpha * constant


class _Job(NamedTuple):
    """One network's training: ``train_network``'s positional arguments."""
    X_tr: np.ndarray
    Y_tr: np.ndarray
    X_va: np.ndarray
    Y_va: np.ndarray
    base: list
    model_cfg: object
    seed: int
    name: str
    prior: object


def _train_models(data, model_cfg, seed, path, validation_fraction, specs, key, progress, priors=None) -> TrainedNets:
    train_idx, val_idx = split_indices(data, validation_fraction, seed, int(model_cfg.batch_size))
    jobs, skipped = [], []
    horizon, delay, frame = int(model_cfg.horizon), int(model_cfg.command_delay), str(model_cfg.frame)
    for i, spec in enumerate(specs):
        X_tr, Y_tr, base = design(data, spec, train_idx, horizon, delay, frame)
        if Y_tr.shape[1] == 0:
            skipped.append(spec.name)
            continue
        X_va, Y_va, _ = design(data, spec, val_idx, horizon, delay, frame)
        ok_tr = np.isfinite(X_tr).all(1) & np.isfinite(Y_tr).all(1)
        ok_va = np.isfinite(X_va).all(1) & np.isfinite(Y_va).all(1)
        if not (ok_tr.all() and ok_va.all()):
            log.warning(f"sdexp: network {spec.name}: dropping {(~ok_tr).sum() + (~ok_va).sum()} non-finite transitions")
            X_tr, Y_tr, X_va, Y_va = X_tr[ok_tr], Y_tr[ok_tr], X_va[ok_va], Y_va[ok_va]
        alpha = int(model_cfg.horizon) * float(data.meta["control_dt"])
        prior = prior_maps(spec, priors, X_tr.shape[1], int(data.meta["m"]), alpha)
        jobs.append(_Job(X_tr, Y_tr, X_va, Y_va, base, model_cfg, int(seed) * 1000 + i, spec.name, prior))
    t0 = time.perf_counter()
    if int(model_cfg.threads) >= 2 and len(jobs) >= 2:
        results = _train_parallel(jobs, int(model_cfg.epochs), progress)
    else:
        results = [train_network(*job, progress=progress) for job in jobs]
    wall = time.perf_counter() - t0
    nets, history, seconds = {}, {}, {}
    for job, (net, hist, sec) in zip(jobs, results):
        name = job.name
        nets[name], history[name], seconds[name] = net, hist, sec
        if progress:
            kept = hist[hist["selected"]].iloc[0]
            log.info(f"sdexp: trained {name} in {sec:.1f} s; kept epoch {int(kept['epoch'])}: validation L1 "
                  f"{kept['val_l1']:.4f} (normalised), {kept['val_rel_l1']:.4f} of copying the velocity")
    result = TrainedNets(nets, history, seconds, key, False, specs, skipped, wall)
    if path is not None:
        _save(path, key, result)
    return result


# ------------------------------------------------------------------------------ parallel training

def _train_job(*args, report):
    net, hist, sec = train_network(*args, progress=False, report=report, threads=1)
    return net.spec(), net.state_dict(), hist.to_dict(orient="list"), sec


def _train_parallel(jobs, epochs: int, progress: bool):
    """Every network in its own one-thread process, all at once (sdexp.parallel).

    Why not one process with ``model.threads`` torch threads, one network after the other: on
    this 2-core machine the networks' matrices (512 x 128) are too small for two threads to pay
    (measured 1.5 s/epoch on 2 threads vs 2.0 s on 1), and a second busy process makes
    OpenMP's barriers collapse (10-30 s/epoch measured); three one-thread processes share two
    cores at 2/3 speed each and degrade gracefully under load."""
    from sdexp.log import Phase

    names = ", ".join(job.name for job in jobs)
    with Phase(f"training nets {names} (one process each)", total=epochs * len(jobs), unit="epochs",
               enabled=progress) as bar:
        latest = {}

        def epoch_done(row: dict) -> None:
            """A worker's epoch: counted, its losses shown in the progress lines beside the others'."""
            latest[row["net"]] = f"epoch {row['epoch']} train {row['train']:.4f} val {row['val']:.4f}"
            bar.set_postfix(**latest)
            bar.update()
        results = run_spawned(_train_job, jobs, len(jobs), epoch_done)
    return [(ResidualMLP.from_saved(spec, state), pd.DataFrame(hist), sec) for spec, state, hist, sec in results]


def history_table(trained: TrainedNets) -> pd.DataFrame:
    """One long table of every network's curves (network, epoch, lr, train_loss, val_loss, val_l1)."""
    return pd.concat([h.assign(network=n) for n, h in trained.history.items()], ignore_index=True)[
        ["network", "epoch", "lr", "train_loss", "val_loss", "val_l1", "val_rel_l1", "seconds", "selected"]]


def loss_plot(trained: TrainedNets, path: Path, title: str = "training curves") -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(6, 4))
    for (n, h), c in zip(trained.history.items(), ("tab:blue", "tab:orange", "tab:green", "tab:red")):
        ax.plot(h["epoch"], h["train_loss"], color=c, ls="--", label=f"{n} train")
        ax.plot(h["epoch"], h["val_loss"], color=c, label=f"{n} validation")
        if "selected" in h and h["selected"].any():
            sel = h[h["selected"]]
            ax.plot(sel["epoch"], sel["val_loss"], "o", color=c, mfc="none", ms=8)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (standardised velocity change)")
    ax.set_title(f"{title} (o: epoch kept)" if any("selected" in h for h in trained.history.values()) else title)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=120)

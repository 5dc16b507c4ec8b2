"""``sdexp experiment=ablation_decomposition``: the paper's "Ablation Testing: State
Decomposition". The same networks trained without the decomposition, on the same data.

Decomposed: d, g, h on (s, s_dot, e, e_dot, p_dot, u) as in Eq. 4, predicting s_dot_next,
e_dot_next, p_dot_next (n_s + n_e + dim channels). Undecomposed: one network of the same
architecture (``model.hidden`` wide unless ``experiment.params.raw_hidden`` says otherwise,
``model.blocks`` blocks) fed the concatenated raw state -- position, central orientation and
every peripheral IMU's world-frame orientation (the dataset's ``raw``), their rates
(``raw_dot``) and u -- predicting ``raw_dot_next`` (dim + n_e (1 + n_s) channels). Same
transitions, same episode split, same optimiser, schedule, batch size, epochs and loss
(``model.*``), same seed.

What is compared. The two formulations predict different quantities, so their raw losses are
not comparable. Both are scored by the same dimensionless number, the *relative validation L1*:
on the held-out episodes, for every target channel c,

    rel_L1_c = mean |pred_next_c - next_c| / mean |current_c - next_c|,

the network's mean absolute error over that of predicting "no change" (copying the current
velocity), averaged over all channels of the formulation (for d, g, h together every channel
counts once: the networks' values weighted by their channel counts). 1 means the network has
learned nothing beyond copying its input, 0 a perfect prediction. Both the error and its
reference are L1, so the score does not depend on how heavy-tailed a channel is. (Normalising
by the standard deviation of the change instead -- the loss the networks train on -- would
flatter the undecomposed network: most of its channels are peripheral Euler rates whose changes
are near zero except for huge spikes near the gimbal lock, so even copying scores ~0.15 there.)

Two comparisons, both in the CSV, the plot and the metrics:
  shared  the channels both formulations predict with the very same targets: the central
          orientation rates e_dot and the velocity p_dot (g, h against the matching columns of
          the raw network's output). Same targets, so only the inputs (and the split into
          networks) differ: the cleanest test of the decomposition.
  all     every channel of each formulation: d, g, h's s_dot, e_dot, p_dot (n_s + n_e + dim)
          against the raw network's p_dot, e_dot and peripheral orientation rates
          (dim + n_e (1 + n_s)). Different targets: bend rates s_dot, from which the common
          rigid rotation is removed, are harder to predict than world-frame rates.
Output: ``ablation_decomposition.csv`` (per epoch: both formulations' relative validation L1 on
both channel sets, their training losses, and d, g, h separately), ``ablation_decomposition.png``,
and the ratio undecomposed / decomposed (> 1: the decomposition helps) at the last epoch
(``*_ratio_undecomposed_over_decomposed``) and between the curves' minima (``*_ratio_best``).
The undecomposed network has the same width and depth as each of d, g, h, so about a third of
their parameters together (``experiment.params.raw_hidden`` widens it).
"""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pandas as pd

from sdexp.model.specs import DECOMPOSED, UNDECOMPOSED
from sdexp.model.training import design, train_models
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def _param_count(nets) -> int:
    return int(sum(p.numel() for net in nets.values() for p in net.parameters()))


def combined_curve(trained, column: str) -> np.ndarray:
    """Channel-weighted mean of the networks' per-epoch ``column``."""
    tot, width = 0.0, 0
    for spec in trained.specs:
        if spec.name not in trained.history:
            continue
        w = trained.nets[spec.name].n_out
        tot = tot + w * trained.history[spec.name][column].to_numpy()
        width += w
    return tot / width


def run(run: Run) -> dict:
    from sdexp.model.dataset import load_dataset

    cfg, p = run.cfg, run.params
    seed, vf = int(cfg.seed), float(cfg.data.validation_fraction)
    data = load_dataset(cfg)
    dec = train_models(data, cfg.model, seed, cfg.cache_dir, vf, DECOMPOSED)
    raw_model = replace(cfg.model, hidden=int(p.raw_hidden or cfg.model.hidden))
    raw = train_models(data, raw_model, seed, cfg.cache_dir, vf, UNDECOMPOSED)

    _, val_idx = data.split(vf, seed)
    shared = shared_channels(data)
    table = _curves(dec, raw, shared)
    widths = {s.name: design(data, s, val_idx[:1])[1].shape[1] for s in (*DECOMPOSED, *UNDECOMPOSED)}
    run.table(table, "ablation_decomposition")
    run.figure(_figure(table, shared is not None, cfg.drone.name), "ablation_decomposition")

    def final_best(col: str) -> tuple[float, float]:
        return float(table[col].iloc[-1]), float(table[col].min())

    out = {}
    for kind in (["shared"] if shared is not None else []) + ["all"]:
        col = "{}_shared_val_rel_l1" if kind == "shared" else "{}_val_rel_l1"
        (d_final, d_best), (r_final, r_best) = final_best(col.format("decomposed")), final_best(col.format("undecomposed"))
        out.update({f"{kind}_decomposed_val_rel_l1": d_final, f"{kind}_undecomposed_val_rel_l1": r_final,
                    f"{kind}_ratio_undecomposed_over_decomposed": r_final / d_final,
                    f"{kind}_decomposed_val_rel_l1_best": d_best, f"{kind}_undecomposed_val_rel_l1_best": r_best,
                    f"{kind}_ratio_best": r_best / d_best})
    log.info(table.iloc[[0, len(table) // 2, -1]].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    out.update({
        "decomposed_channels": int(sum(widths[s] for s in dec.nets)), "undecomposed_channels": int(widths["raw"]),
        "decomposed_parameters": _param_count(dec.nets), "undecomposed_parameters": _param_count(raw.nets),
        "decomposed_train_wall_seconds": float(dec.wall_seconds),
        "undecomposed_train_wall_seconds": float(raw.wall_seconds),
        "epochs": int(cfg.model.epochs),
    })
    return out


def _curves(dec, raw, shared) -> pd.DataFrame:
    """Per epoch, both formulations' validation error (of copying) and training loss, on their
    own targets and, where the raw state holds them, on the targets both predict."""
    table = pd.DataFrame({"epoch": dec.history[next(iter(dec.history))]["epoch"]})
    table["decomposed_val_rel_l1"] = combined_curve(dec, "val_rel_l1")
    table["undecomposed_val_rel_l1"] = raw.history["raw"]["val_rel_l1"].to_numpy()
    if shared is not None:
        rel = lambda t, n: np.array(t.history[n]["val_rel_l1_channels"].tolist())  # noqa: E731
        dec_shared = np.concatenate([rel(dec, "g"), rel(dec, "h")], axis=1)          # e_dot, p_dot
        raw_shared = rel(raw, "raw")[:, shared]                                        # the same targets
        table["decomposed_shared_val_rel_l1"] = dec_shared.mean(1)
        table["undecomposed_shared_val_rel_l1"] = raw_shared.mean(1)
    table["decomposed_train_loss"] = combined_curve(dec, "train_loss")
    table["undecomposed_train_loss"] = raw.history["raw"]["train_loss"].to_numpy()
    for n, h in dec.history.items():
        table[f"{n}_val_rel_l1"] = h["val_rel_l1"].to_numpy()
    return table


def _figure(table: pd.DataFrame, shared: bool, drone: str):
    """The two formulations' validation curves: on the shared targets (where there are) and on
    each one's own."""
    from sdexp.figures import pyplot
    plt = pyplot()
    panels = [("all", "each formulation's own targets")]
    if shared:
        panels.insert(0, ("shared", "the targets both predict: e_dot, p_dot"))
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 4.2), squeeze=False)
    for ax, (kind, title) in zip(axes[0], panels):
        col = "{}_shared_val_rel_l1" if kind == "shared" else "{}_val_rel_l1"
        dcol, rcol = col.format("decomposed"), col.format("undecomposed")
        ax.plot(table["epoch"], table[dcol], color="tab:blue", lw=2, label="decomposed (d, g, h)")
        ax.plot(table["epoch"], table[rcol], color="tab:red", lw=2, label="undecomposed (raw state)")
        ax.axhline(1.0, color="k", ls="--", lw=0.8, label="copying the current velocity")
        ax.set_xlabel("epoch")
        ax.set_ylabel("validation L1 / L1 of \"no change\"")
        ax.set_ylim(0, max(1.1, float(table[[dcol, rcol]].max().max()) * 1.05))
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{drone}: convergence with and without the state decomposition", fontsize=11)
    fig.tight_layout()
    return fig


def shared_channels(data) -> np.ndarray | None:
    """Columns of raw_dot_next that are e_dot_next and p_dot_next, in the order g, h predict
    them (the dataset's raw state starts with p, then the frame Euler angles); None when the
    arrays say otherwise."""
    a = data.arrays
    dim, n_e = a["p_dot_next"].shape[1], a["e_dot_next"].shape[1]
    cols = np.r_[np.arange(dim, dim + n_e), np.arange(dim)]
    raw = a["raw_dot_next"]
    if raw.shape[1] < dim + n_e or not np.array_equal(raw[:, cols], np.concatenate([a["e_dot_next"], a["p_dot_next"]], 1)):
        log.warning("sdexp: raw_dot_next does not start with (p_dot, e_dot): no shared-target comparison")
        return None
    return cols

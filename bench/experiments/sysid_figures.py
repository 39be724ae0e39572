"""System identification (paper Figures 8 and 9, Algorithms D.2, D.4) and a linear probe of G_ID.

Figure 8 (Pendulum, Cartpole, Cheetah, JACO; parameterized data, one sampled instance per
sequence): rollout error normalized to the constant baseline of four models, all rolled out from
step W (= the window, 20) of each test sequence for the rest of it (80 steps of 100):

  no params    a fixed-system forward model trained on the varied data: its ``FeatureLayout`` is
               the fixed system's and its graph builder gives every sequence the fixed system's
               static graph (``fixed_system`` below), so it never sees the parameters;
  true params  the forward model on the parameterized layout (the true static graph);
  sysid same   ``SysIDModel``: G_ID from steps [0, W) of the same sequence (same instance);
  sysid other  G_ID from steps [0, W) of another test sequence (another instance).

Goal: sysid same within 1.2x of true params, and clearly below no params.

Figure 9 (Pendulum): the pendulum sysid model of Figure 8 on new instances of fixed mass (1.0)
and given lengths (the length is never observed: no static feature reaches the model). Each
instance is simulated twice from the same initial states: under random spline controls
throughout ("with controls"), and with the controls of the identification window [0, W) set to
zero ("without controls", a passive window; the same controls after it). G_ID from the window,
rollouts from step W; errors per length and condition, true vs predicted pendulum angle plotted.

Probe (beyond the paper): a least-squares (small ridge) linear map from G_ID (globals, node
latents mean-pooled over the movable bodies, edge latents mean-pooled) to the instance's true
parameters (``ds.static["params"]``, names in ``ds.meta["param_names"]``), fitted on G_IDs of
train sequences (first window) and scored by R^2 per parameter on the test sequences.

    python bench/experiments/sysid_figures.py --quick                       # CPU smoke run (about 1 min)
    python bench/experiments/sysid_figures.py --systems pendulum --seconds 120
    python bench/experiments/sysid_figures.py --systems cartpole --seconds 120    # one system a call
    python bench/experiments/sysid_figures.py --compare --out DIR   # DIR's --label runs side by side

Each system trains three models (no params, true params, sysid), each capped at ``--seconds``
of wall clock (and ``--steps`` steps; learning rate x0.6 every quarter of ``--steps``). One
system per call fits a 10-minute command at ``--seconds 120``. Every measured row (errors, probe,
per-sequence shares) is appended to ``results.jsonl``, and the Figure 8 and 9 errors as results
records (``gnwarp.eval.records``) to ``records.jsonl``. ``summary.md`` (the errors) is generated
from all records there by ``gnwarp.eval.summarize`` (the last record of each system / model
stands), ``fig8.png`` from the same records, and ``probe.md`` from the newest probe, estimate and
spread rows, so systems can run in separate calls. A pendulum run also draws
``fig9.png`` (``fig9_<label>.png`` with ``--label``, so that labelled runs sharing ``--out`` keep
their own). Datasets are cached under ``--data`` (default: a temporary folder), checkpoints under
``--runs`` (default: a temporary folder).
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import device_name, experiment_out, gn_sizes  # noqa: E402
from gnwarp.train.sysid_config import SYSID_MODEL_FLAGS, add_sysid_arguments, sysid_settings  # noqa: E402

SYSTEMS = ["pendulum", "cartpole", "cheetah", "jaco"]
MODELS = ("no params", "true params", "sysid same", "sysid other")
FIG9_LENGTHS = (0.3, 0.6, 0.9)


# -- models ---------------------------------------------------------------------------------------
def fixed_system(model, system: str):
    """``model`` (on the fixed system's layout) reading every dataset as the fixed system: its
    graph builder gives each instance the fixed system's static graph, whatever the instance's
    parameters. (Mapping the parameterized data onto the fixed layout with ``strict=False`` is
    not enough: columns that vary across bodies, e.g. a pendulum's body mass and inertia, stay
    kept columns of the fixed layout and would carry the parameters.) Set on the instance, so the
    Trainer's sampler, its validation and ``gnwarp.eval`` all use it."""
    from types import SimpleNamespace

    from gnwarp.data import static_arrays
    from gnwarp.models import ForwardModel
    from gnwarp.sim import make
    static, layout, _ = static_arrays([make(system)])

    def graph_builder(source, strict: bool = True):
        if not hasattr(source, "static"):      # a System: its own static graph
            return ForwardModel.graph_builder(model, source, strict)
        I = np.asarray(source.static["n_node"]).shape[0]
        tiled = {k: np.repeat(np.asarray(v)[:1], I, 0) for k, v in static.items()}
        for k in ("senders", "receivers", "n_node", "n_edge", "edge_ctrl"):
            if not np.array_equal(tiled[k], np.asarray(source.static[k])):
                raise ValueError(f"{system}: the data's instances do not all have the fixed system's topology ({k})")
        view = SimpleNamespace(static=tiled, layout=layout, meta=source.meta)
        return ForwardModel.graph_builder(model, view, strict)
    model.graph_builder = graph_builder
    return model


def fixed_layout(system: str):
    """The fixed system's ``FeatureLayout`` (the parameters are dropped constants there)."""
    from gnwarp.data import static_arrays
    from gnwarp.sim import make
    return static_arrays([make(system)])[1]


def model_config(args, ds):
    from gnwarp.models import ModelConfig
    from gnwarp.models.config import DEFAULT_RUN
    run = DEFAULT_RUN.replace(impl=args.impl, **({"precision": args.precision} if args.precision else {}))
    return ModelConfig(gn=gn_sizes(args.latent, args.edge_width, args.node_width), run=run,
                       recenter=bool(ds.meta.get("translation_invariant", False)))


def train_config(args, out, ds):
    from gnwarp.train import TrainConfig
    return TrainConfig(out=str(out), model=model_config(args, ds), steps=args.steps, max_seconds=args.seconds,
                       batch_size=args.batch, lr=args.lr, lr_decay=0.6, lr_decay_steps=max(1, args.steps // 4),
                       valid_every=args.valid_every, valid_sequences=min(args.valid, len(ds["valid"])),
                       patience=None, checkpoint_every=max(1, args.steps), resume=False, progress=False,
                       device=args.device, seed=args.seed, normalizer_warmup=args.normalizer_warmup,
                       capture=not args.no_capture, ema=args.ema,
                       **({} if args.noise is None else {"noise_std": args.noise}))


def cfg_noise(args) -> float:
    from gnwarp.train import TrainConfig
    return TrainConfig().noise_std if args.noise is None else float(args.noise)


def identifier_config(args):
    """GN_p's sizes from --gid and --identifier-*; ``sysid_settings`` applies --gid-globals."""
    from gnwarp.models import RecurrentGNConfig
    g, mlp = args.gid, tuple(args.identifier_mlp)
    return RecurrentGNConfig(latent=args.identifier_latent, hidden_edges=g, hidden_nodes=g, hidden_globals=g,
                             out_edges=g, out_nodes=g, out_globals=g, edge_mlp=mlp, node_mlp=mlp, global_mlp=mlp)


def sysid_config(args):
    """(``SysIDConfig``, ``SysIDTrainConfig``) of the sysid model from the shared flags."""
    return sysid_settings(args, identifier_config(args), window=args.window)


def train_all(args, ds, system: str, runs: Path) -> tuple[dict, dict]:
    """The three models of one system, trained on ``ds``: ({label: model}, {label: train summary})."""
    from gnwarp.models import ForwardModel
    from gnwarp.train import Trainer, load_model
    from gnwarp.train.sysid import SysIDTrainer, load_sysid

    models, info = {}, {}
    cfg = train_config(args, runs / system / "no_params", ds)
    nop = fixed_system(ForwardModel(cfg.model, fixed_layout(system)), system)
    r = Trainer(cfg, datasets=[ds], model=nop).run()
    models["no params"], info["no params"] = fixed_system(load_model(r["best"], device=args.device), system), r

    cfg = train_config(args, runs / system / "true_params", ds)
    r = Trainer(cfg, datasets=[ds]).run()
    models["true params"], info["true params"] = load_model(r["best"], device=args.device), r
    # further true-parameter models, identically configured: the reference's run-to-run spread
    models["true params runs"] = [models["true params"]]
    for k in range(1, args.reference_runs):
        r = Trainer(train_config(args, runs / system / f"true_params_{k}", ds), datasets=[ds]).run()
        models["true params runs"].append(load_model(r["best"], device=args.device))

    cfg = train_config(args, runs / system / "sysid", ds)
    sysid, options = sysid_config(args)
    r = SysIDTrainer(cfg, sysid, datasets=[ds], options=options).run()
    models["sysid"], info["sysid"] = load_sysid(r["best"], device=args.device), r
    for m in [*models.values(), *models["true params runs"]]:
        if not isinstance(m, list):
            m.eval()
    return models, info


# -- errors ---------------------------------------------------------------------------------------
def split_arrays(ds, split: str, n: int | None):
    sp = ds[split]
    n = len(sp) if n is None else min(int(n), len(sp))
    return (np.asarray(sp.body[:n], dtype=np.float32), np.asarray(sp.ctrl[:n], dtype=np.float32),
            np.asarray(sp.instance[:n]))


@torch.no_grad()
def forward_window_predictions(model, ds, split: str, W: int, horizon: int, n: int | None, batch: int = 1024):
    """A forward model's rollouts as ``sysid_rollout_predictions`` gives sysid's: from step ``W``
    of each of the first ``n`` sequences of ``split`` for ``horizon`` steps (cut to the
    sequences' end), under their true controls: (predicted, true, instance)."""
    body, ctrl, inst = split_arrays(ds, split, n)
    H = min(int(horizon), ctrl.shape[1] - W)
    builder = model.graph_builder(ds)
    preds = []
    for a in range(0, body.shape[0], batch):
        b = slice(a, a + batch)
        r = model.rollout(torch.as_tensor(body[b, W]), torch.as_tensor(ctrl[b, W:W + H]), torch.as_tensor(inst[b]),
                          builder=builder)
        preds.append(r.float().cpu().numpy())
    return np.concatenate(preds), body[:, W:W + H + 1], inst


def fig8_rows(args, system: str, ds, models: dict) -> list[dict]:
    """The Figure 8 errors; and each test sequence's share of the error of every true-parameter
    run, of sysid and of its oracle ("sequences" row, 3 digits, with the test instances'
    parameters): a mean of squared rollout errors can rest on a few sequences."""
    from gnwarp.eval.metrics import movable_mask, rollout_error
    from gnwarp.eval.sysid import other_instance_windows, sysid_rollout_predictions, window_errors
    from gnwarp.train.sysid import trained_options, trained_param_stats
    W, n = args.window, min(args.test, len(ds["test"]))
    H = ds["test"].num_steps - W
    inst = split_arrays(ds, "test", n)[2]
    mask = movable_mask(ds, inst)
    other = other_instance_windows(ds, "test", n)   # sequence i from sequence i-1's window: another instance
    preds = {f"true params {k}": forward_window_predictions(m, ds, "test", W, H, n)
             for k, m in enumerate(models["true params runs"])}
    preds["no params"] = forward_window_predictions(models["no params"], ds, "test", W, H, n)
    preds["sysid same"] = sysid_rollout_predictions(models["sysid"], ds, "test", H, n)
    preds["sysid other"] = sysid_rollout_predictions(models["sysid"], ds, "test", H, n, window_from=other)
    if trained_options(models["sysid"]).param_loss > 0:   # its supervised columns identified perfectly
        preds["oracle"] = sysid_rollout_predictions(models["sysid"], ds, "test", H, n,
                                                    oracle=trained_param_stats(models["sysid"], system))
    errs, shares = {}, {}
    for k, (pred, true, _) in preds.items():
        errs[k], shares[k] = window_errors(pred, true, mask, shares=True)
    runs = [errs[f"true params {k}"] for k in range(len(models["true params runs"]))]
    errs["true params"] = float(np.median(runs))   # one run's, or the median of --reference-runs
    # for reference, the forward models' usual error (rollouts from step 0, ``gnwarp.eval``)
    from_0 = {k: rollout_error(models[k], ds, "test", ds["test"].num_steps, n) for k in ("no params", "true params")}
    rows = [{"part": "fig8", "system": system, "model": k, "error": float(errs[k]), "window": W, "horizon": H,
             "test_sequences": n, "from_step_0": from_0.get(k),
             **({"runs": runs} if k == "true params" else {})} for k in MODELS]
    if "oracle" in errs:
        rows.append({"part": "oracle", "system": system, "model": "sysid, true parameter columns",
                     "error": float(errs["oracle"]),
                     "ratio_to_true": float(errs["oracle"] / errs["true params"]) if errs["true params"] else None,
                     "window": W, "horizon": H, "test_sequences": n})
    params = ds.static.get("params")
    params = None if params is None else [[float(f"{x:.3g}") for x in p] for p in np.asarray(params)[inst]]
    rows.append({"part": "sequences", "system": system, "instances": inst.tolist(),
                 "param_names": list(ds.meta.get("param_names", [])), "params": params,
                 "shares": {k: [float(f"{x:.3g}") for x in v] for k, v in shares.items()
                            if k not in ("no params", "sysid other")}})
    return rows


@torch.no_grad()
def spread_rows(args, system: str, ds, model) -> list[dict]:
    """How much G_ID depends on the window rather than the sequence (``window_spread``): G_ID of
    each test sequence from its first and from its last ``W`` steps."""
    from gnwarp.train.sysid import window_spread
    body, ctrl, inst = split_arrays(ds, "test", args.test)
    W, T = model.window, ctrl.shape[1]
    model.bind(ds)
    g = [model.identify(torch.as_tensor(body[:, a:a + W]), torch.as_tensor(ctrl[:, a:a + W]), torch.as_tensor(inst))
         for a in (0, T - W)]
    return [{"part": "spread", "system": system, "window_spread": float(window_spread(*g)), "windows": [0, T - W],
             "test_sequences": int(body.shape[0])}]


# -- probe ----------------------------------------------------------------------------------------
@torch.no_grad()
def gid_features(model, ds, split: str, n: int | None, batch: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """([S, F] G_ID features of the first ``n`` sequences of ``split``, identified from their
    first window: globals, node latents mean-pooled over the movable bodies, edge latents
    mean-pooled; [S] instances)."""
    body, ctrl, inst = split_arrays(ds, split, n)
    W = model.window
    model.bind(ds)
    feats = []
    for a in range(0, body.shape[0], batch):
        b = slice(a, a + batch)
        g = model.identify(torch.as_tensor(body[b, :W]), torch.as_tensor(ctrl[b, :W]), torch.as_tensor(inst[b]))
        N = g.n_node.shape[0]
        parts = []
        if g.globals is not None:
            parts.append(g.globals.float().cpu().numpy())
        if g.nodes is not None:
            B = int(g.n_node[0])
            parts.append(g.nodes.float().cpu().numpy().reshape(N, B, -1)[:, 1:].mean(1))  # fixed topology per system
        if g.edges is not None:
            E = int(g.n_edge[0])
            parts.append(g.edges.float().cpu().numpy().reshape(N, E, -1).mean(1))
        feats.append(np.concatenate(parts, -1))
    return np.concatenate(feats), inst


def probe_rows(args, system: str, ds, model) -> list[dict]:
    params = np.asarray(ds.static["params"], dtype=np.float64)
    names = list(ds.meta.get("param_names", [f"p{i}" for i in range(params.shape[1])]))
    xtr, itr = gid_features(model, ds, "train", args.probe_train)
    xte, ite = gid_features(model, ds, "test", args.test)
    mu, sd = xtr.mean(0), xtr.std(0) + 1e-8
    A = np.concatenate([(xtr - mu) / sd, np.ones((len(xtr), 1))], 1)
    At = np.concatenate([(xte - mu) / sd, np.ones((len(xte), 1))], 1)
    reg = 1e-3 * np.eye(A.shape[1])
    reg[-1, -1] = 0.0
    rows = []
    for j, name in enumerate(names):
        y, yt = params[itr, j], params[ite, j]
        ok, okt = np.isfinite(y), np.isfinite(yt)
        if ok.sum() < 2 or okt.sum() < 2 or np.var(yt[okt]) == 0:
            continue
        w = np.linalg.solve(A[ok].T @ A[ok] + reg * ok.sum(), A[ok].T @ y[ok])
        res = yt[okt] - At[okt] @ w
        r2 = 1.0 - float(np.mean(res ** 2) / np.var(yt[okt]))
        rows.append({"part": "probe", "system": system, "param": name, "r2": r2, "train": int(ok.sum()),
                     "test": int(okt.sum()), "features": int(A.shape[1] - 1)})
    return rows


@torch.no_grad()
def estimate_rows(args, system: str, ds, model) -> list[dict]:
    """With ``--param-loss``: the parameters G_ID carries (``estimate_params``) against the test
    instances' true ones, from each test sequence's first window: the rms error over the
    parameter's mean magnitude, and R^2."""
    from gnwarp.models.sysid_params import estimate_params
    from gnwarp.train.sysid import trained_param_stats
    body, ctrl, inst = split_arrays(ds, "test", args.test)
    model.bind(ds)
    W = model.window
    g = model.identify(torch.as_tensor(body[:, :W]), torch.as_tensor(ctrl[:, :W]), torch.as_tensor(inst))
    st = trained_param_stats(model, system)    # the statistics it trained with (its config.json)
    est, true = estimate_params(g, st), np.asarray(ds.static["params"], dtype=np.float64)[inst]
    rows = []
    for j, name in enumerate(st.names):
        ok = np.isfinite(est[:, j]) & np.isfinite(true[:, j])
        if ok.sum() < 2:
            continue
        e, t = est[ok, j], true[ok, j]
        rows.append({"part": "estimate", "system": system, "param": name,
                     "rel_rms": float(np.sqrt(np.mean((e - t) ** 2)) / max(np.mean(np.abs(t)), 1e-300)),
                     "r2": float(1.0 - np.mean((e - t) ** 2) / max(np.var(t), 1e-300)), "test": int(ok.sum())})
    return rows


# -- Figure 9 -------------------------------------------------------------------------------------
@torch.no_grad()
def fig9(args, models: dict, out: Path) -> list[dict]:
    """Pendulum instances of given lengths (mass 1): identification windows with and without
    controls, rollouts from step W; rows of errors and the trajectories of one sequence each."""
    from gnwarp.data import initial_states
    from gnwarp.eval.sysid import window_errors
    from gnwarp.sim import control_range, make, random_spline_controls, simulate
    sysid, true_m = models["sysid"], models["true params"]
    W, T, n = args.window, args.num_steps, args.fig9_sequences
    H = T - W
    rows, traces = [], {}
    for k, L in enumerate(args.fig9_lengths):
        system = make("pendulum", params={"length": float(L), "mass": 1.0})
        rng = np.random.default_rng(args.seed + 1000 + k)
        q0, v0 = initial_states(system, n, rng)
        u = random_spline_controls(n, T, control_range(system.model), rng).astype(np.float32)
        passive = u.copy()
        passive[:, :W] = 0.0
        sysid.bind(system)
        builder = true_m.graph_builder(system)
        for cond, uu in (("with controls", u), ("without controls", passive)):
            body = simulate(system, q0, v0, uu, backend=args.backend).body.astype(np.float32)
            mask = np.broadcast_to(np.arange(body.shape[2])[None] >= 1, (n, body.shape[2]))
            g = sysid.identify(torch.as_tensor(body[:, :W]), torch.as_tensor(uu[:, :W]))
            pred = sysid.rollout(torch.as_tensor(body[:, W]), torch.as_tensor(uu[:, W:W + H]), g).float().cpu().numpy()
            ref = true_m.rollout(torch.as_tensor(body[:, W]), torch.as_tensor(uu[:, W:W + H]),
                                 torch.zeros(n, dtype=torch.int64), builder=builder).float().cpu().numpy()
            true = body[:, W:W + H + 1]
            rows.append({"part": "fig9", "system": "pendulum", "length": float(L), "condition": cond,
                         "sysid": window_errors(pred, true, mask), "true params": window_errors(ref, true, mask),
                         "fig9_sequences": n, "window": W, "horizon": H})
            traces[(float(L), cond)] = (body[0], pred[0], ref[0], uu[0])
    plot_fig9(traces, args.fig9_lengths, W, out / (f"fig9_{args.label}.png" if args.label else "fig9.png"))
    return rows


def pendulum_angle(body: np.ndarray) -> np.ndarray:
    """The pole's hinge angle (about y) of states [T, B, 13], unwrapped."""
    q = body[:, 1]
    return np.unwrap(2.0 * np.arctan2(q[:, 5], q[:, 3]))


def plot_fig9(traces: dict, lengths, W: int, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    conds = ("with controls", "without controls")
    fig, axes = plt.subplots(2, len(lengths), figsize=(4.2 * len(lengths), 6.4), squeeze=False, sharex=True)
    for i, cond in enumerate(conds):
        for j, L in enumerate(lengths):
            ax = axes[i, j]
            body, pred, ref, u = traces[(float(L), cond)]
            t = np.arange(body.shape[0])
            a = pendulum_angle(body)
            ax.axvspan(0, W, color="0.9", label="identification window")
            ax.plot(t, a, "k", label="true")
            off = a[W] - pendulum_angle(pred)[0]    # the same branch of the unwrapped angle
            ax.plot(t[W:], pendulum_angle(pred) + off, "C1", label="sysid (G_ID)")
            ax.plot(t[W:], pendulum_angle(ref) + (a[W] - pendulum_angle(ref)[0]), "C2--", lw=1, label="true params")
            ax2 = ax.twinx()
            ax2.plot(t[:-1], u[:, 0], color="C0", alpha=0.3, lw=0.8)
            ax2.set_yticks([])
            ax.set_title(f"length x{L:g}, {cond}", fontsize=9)
            if j == 0:
                ax.set_ylabel("angle (rad)")
            if i == 1:
                ax.set_xlabel("step")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle("Figure 9: Pendulum (length unobserved), identification with / without control inputs "
                 "(controls in light blue)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- results --------------------------------------------------------------------------------------
def latest(rows: list[dict]) -> list[dict]:
    """The newest row of each (part, system, model / param / length + condition), in first-seen order."""
    keep = {}
    for r in rows:
        keep[(r["part"], r["system"], r.get("model"), r.get("param"), r.get("length"), r.get("condition"))] = r
    return list(keep.values())


def _g(x) -> str:
    return "-" if x is None else ("inf" if not math.isfinite(x) else f"{x:.3g}")


# keys of a row that the record holds in its own fields (the rest go to its config)
_ROW_FIELDS = {"part", "system", "model", "error", "window", "horizon", "test_sequences", "fig9_sequences",
               "from_step_0", "runs", "steps", "train_seconds", "ratio_to_true", "device", "date", "length",
               "condition", "sysid", "true params"}


def to_records(rows: list[dict], commit: str = "unknown") -> list:
    """The error rows of this script (parts "fig8", "oracle", "fig9") as results records (``gnwarp.eval.records``):
    planner "none" on learned dynamics, the model as the variant ("no params", "true params", "sysid same",
    "sysid other", "sysid, true parameter columns"; with the run's ``--label`` in brackets), each a
    reported mean error over the test sequences (per-sequence errors are not kept; std null). Figure 8
    and oracle records have the system as their task; Figure 9's are tasks "pendulum length xL, <condition>"
    with variants "sysid same" and "true params". Episode steps: the rollout horizon. Metrics: the
    models' training steps and seconds, the error of rollouts from step 0, the reference runs' errors;
    a labelled run's "sysid same" record whose run kept its per-sequence errors (a "sequences" row)
    adds the ratio's two paired readings (``paired_ratios``): ``ratio_without_top_1pct`` and
    ``ratio_median_per_sequence``; and its parameter estimates' relative rms errors
    (``estimate_rel_rms``, {parameter: error}) and linear probe's R^2 (``probe_r2``). The seed: the row's, or the "s<K>-" that starts a run's label
    (``--seed K --label sK-...``); None otherwise. Numbers unchanged; rows of other parts give no record."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    paired = {(r["run"], r["system"]): paired_ratios(r["shares"]) for r in rows
              if r.get("part") == "sequences" and r.get("run")}
    # a labelled run's parameter estimates (relative rms error) and linear probe (R^2), per parameter
    estimates: dict[tuple, dict] = {}
    probes: dict[tuple, dict] = {}
    for r in rows:
        if r.get("part") == "estimate" and r.get("run") and r.get("rel_rms") is not None:
            estimates.setdefault((r["run"], r["system"]), {})[r["param"]] = r["rel_rms"]
        if r.get("part") == "probe" and r.get("run") and r.get("r2") is not None:
            probes.setdefault((r["run"], r["system"]), {})[r["param"]] = r["r2"]
    out = []
    for r in rows:
        part = r.get("part")
        if part not in ("fig8", "oracle", "fig9"):
            continue
        system = systems.make(r["system"])
        seqs = r.get("sequences")
        config = {k: v for k, v in r.items() if k not in _ROW_FIELDS}
        config["window"] = r["window"]
        run = f" [{r['run']}]" if r.get("run") else ""
        # the run's seed: its row's, or a label's "s<K>-" (the runs' commands: --seed K --label sK-...)
        seed = r.get("seed")
        if seed is None and re.match(r"s\d+-", r.get("run") or ""):
            seed = int(re.match(r"s(\d+)-", r["run"]).group(1))
        common = dict(seed=seed, experiment="sysid_figures" + ("/fig9" if part == "fig9" else ""),
                      system=r["system"],
                      planner="none", dynamics="learned", episode_steps=int(r["horizon"]),
                      control_dt=float(system.dt), action_repeat=int(system.substeps),
                      env_steps=int(seqs[0]) * (int(r["window"]) + int(r["horizon"])) if seqs else None,
                      config=config, commit=commit, gpu=r.get("device", "unknown"), date=r.get("date", ""))
        if part == "fig9":
            task = f"pendulum length x{r['length']:g}, {r['condition']}"
            for model, variant in (("sysid", "sysid same"), ("true params", "true params")):
                if r.get(model) is None:
                    continue
                out.append(ResultRecord(task=task, variant=variant + run, episodes=int(r["fig9_sequences"]),
                                        reported={"mean": float(r[model]), "std": None, "of": "errors"}, **common))
            continue
        metrics = {k: v for k, v in (("train_steps", r.get("steps")), ("train_seconds", r.get("train_seconds")),
                                      ("from_step_0", r.get("from_step_0")),
                                      ("ratio_to_true", r.get("ratio_to_true")), ("runs", r.get("runs")))
                   if v is not None}
        if r["model"] == "sysid same" and (r.get("run"), r["system"]) in paired:
            trimmed, per_sequence = paired[r["run"], r["system"]]
            metrics.update(ratio_without_top_1pct=trimmed, ratio_median_per_sequence=per_sequence)
        if r["model"] == "sysid same" and (r.get("run"), r["system"]) in estimates:
            metrics["estimate_rel_rms"] = estimates[r["run"], r["system"]]
        if r["model"] == "sysid same" and (r.get("run"), r["system"]) in probes:
            metrics["probe_r2"] = probes[r["run"], r["system"]]
        out.append(ResultRecord(task=r["system"], variant=r["model"] + run, episodes=int(r["test_sequences"]),
                                reported={"mean": float(r["error"]), "std": None, "of": "errors"},
                                metrics=metrics, **common))
    return out


# the summary's ratio column: sysid from the same sequence's window against the true parameters
RATIO = ("none (learned, sysid same)", "none (learned, true params)")


def write_summary(out: Path, records: list, quick: bool = False) -> Path:
    """``summary.md`` from the records (``gnwarp.eval.summarize``): Figure 8 and 9 errors."""
    from gnwarp.eval.summarize import write_summary as summarize
    title = (f"System identification, Figures 8 and 9: rollout errors ({records[-1].gpu if records else '?'}"
             f"{', QUICK smoke run: numbers meaningless' if quick else ''})")
    return summarize(records, out, title, ratio_of=RATIO, plot=False)


def write_probe(out: Path, rows: list[dict]) -> None:
    """``probe.md``: the linear probe of G_ID (R^2 per parameter), the parameters read from G_ID
    (``--param-loss``) and G_ID's spread across windows, from the newest rows of ``results.jsonl``."""
    lines = ["# System identification: what G_ID carries", "",
             "Generated by `python bench/experiments/sysid_figures.py` from the probe, estimate and spread rows of "
             "`results.jsonl` (the newest of each system and parameter). Errors of Figures 8 and 9: `summary.md`."]
    pr = [r for r in rows if r["part"] == "probe"]
    if pr:
        lines += ["", "## Linear probe: G_ID -> true parameters (R^2 on test instances)", "",
                  "Least squares (ridge 1e-3) on standardized G_ID features (globals, mean node and edge latents), "
                  "fitted on train sequences' G_IDs.", "", "| system | parameter | R^2 | train / test |",
                  "|---|---|---|---|"]
        for r in pr:
            lines.append(f"| {r['system']} | {r['param']} | {r['r2']:.3f} | {r['train']} / {r['test']} |")
    es = [r for r in rows if r["part"] == "estimate"]
    if es:
        lines += ["", "## Parameters read from G_ID (`--param-loss`, `estimate_params`)", "",
                  "From each test sequence's first window; relative error: rms error / mean |parameter|.", "",
                  "| system | parameter | relative rms error | R^2 |",
                  "|---|---|---|---|"]
        lines += [f"| {r['system']} | {r['param']} | {r['rel_rms']:.3g} | {r['r2']:.3f} |" for r in es]
    sp = [r for r in rows if r["part"] == "spread"]
    if sp:
        lines += ["", "## G_ID across windows", "",
                  "`window_spread`: the share of G_ID's variance over test sequences that lies between a sequence's "
                  "first and last window (0: G_ID depends only on the sequence's system).", "",
                  "| system | window_spread |", "|---|---|"]
        lines += [f"| {r['system']} | {r['window_spread']:.3f} |" for r in sp]
    (out / "probe.md").write_text("\n".join(lines) + "\n")


def plot_fig8(out: Path, records: list) -> None:
    """``fig8.png``: each system's Figure 8 errors (the records' last of each system and model)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    f8 = [r for r in records if r.experiment == "sysid_figures" and r.variant in MODELS]
    systems = list(dict.fromkeys(r.task for r in f8))
    if not systems:
        return
    err = {(r.task, r.variant): r.reported["mean"] for r in f8}
    x = np.arange(len(systems))
    w = 0.2
    fig, ax = plt.subplots(figsize=(2.2 + 1.8 * len(systems), 3.8))
    for i, k in enumerate(MODELS):
        ax.bar(x + (i - 1.5) * w, [err.get((s, k), np.nan) for s in systems], w, label=k)
    ax.axhline(1.0, color="k", lw=0.8, ls=":", label="constant")
    ax.set_yscale("log")
    ax.set_xticks(x, systems)
    ax.set_ylabel(f"{f8[0].episode_steps}-step rollout error / constant")
    ax.set_title("Figure 8: system identification", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "fig8.png", dpi=110)
    plt.close(fig)


def paired_ratios(shares: dict[str, list[float]], trim: float = 0.01) -> tuple[float, float]:
    """Sysid against its reference sequence by sequence, from a "sequences" row's ``shares``: the
    reference is the true-parameter run of median error (the Figure 8 "true params" with an odd
    ``--reference-runs``, as every recorded run had; with an even count Figure 8 averages the two
    middle runs' errors and this takes the upper one). Returns
    (the error ratio without the ``trim`` share of sequences, at least one, on which the two
    models' errors together are largest; the median over sequences of the per-sequence ratio):
    two readings of the Figure 8 ratio that a few far-drifting rollouts cannot decide."""
    refs = [np.asarray(v) for k, v in shares.items() if k.startswith("true params")]
    ref = refs[int(np.argsort([x.sum() for x in refs])[len(refs) // 2])]
    sysid = np.asarray(shares["sysid same"])
    drop = np.argsort(-(sysid + ref))[:max(1, int(round(trim * len(ref))))]
    trimmed = float(np.delete(sysid, drop).sum() / np.delete(ref, drop).sum())
    return trimmed, float(np.median(sysid / ref))


def compare_runs(out: Path, rows: list[dict]) -> str:
    """``compare.md`` and ``compare.png`` of the Figure 8 runs labelled with a ``run`` (``--label``): per
    system, each run's errors and its sysid / true-params ratio, side by side; where the run
    recorded its per-sequence shares, the ratio's two paired readings (``paired_ratios``). The
    table is generated from ``records.jsonl`` (``bench/results_tables.py``, block "sysid-compare"),
    the plot from ``rows``. Returns the table."""
    from bench import results_tables
    f8 = [r for r in rows if r["part"] == "fig8" and r.get("run")]
    if not f8:
        raise SystemExit(f"--compare: no Figure 8 row with a run label in {out / 'results.jsonl'}")
    runs = list(dict.fromkeys(r["run"] for r in f8))
    systems = list(dict.fromkeys(r["system"] for r in f8))
    cell = {(r["run"], r["system"], r["model"]): r for r in f8}   # newest row of each wins
    ratio = {(run, s): cell[run, s, "sysid same"]["error"] / cell[run, s, "true params"]["error"]
             for s in systems for run in runs if (run, s, "sysid same") in cell and (run, s, "true params") in cell}
    doc = out / "compare.md"
    doc.write_text("<!-- results:begin sysid-compare -->\n<!-- results:end sysid-compare -->\n")
    results_tables.run(files=[doc])
    table = doc.read_text()
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    # runs whose labels differ only in a leading seed ("s2-...") are one setting: a bar at their median
    # ratio, a dot per run; each system shows only the settings it ran
    setting = {run: re.sub(r"^s\d+-", "", run) for run in runs}
    groups = list(dict.fromkeys(setting.values()))
    color = {g: plt.get_cmap("tab20")(i % 20) for i, g in enumerate(groups)}
    fig, ax = plt.subplots(figsize=(2.2 + 1.8 * len(systems), 3.8))
    shown = set()
    for xs, s in enumerate(systems):
        here = [g for g in groups if any((run, s) in ratio and setting[run] == g for run in runs)]
        w = 0.8 / max(1, len(here))
        for i, g in enumerate(here):
            vals = [ratio[run, s] for run in runs if setting[run] == g and (run, s) in ratio]
            at = xs + (i - (len(here) - 1) / 2) * w
            ax.bar(at, float(np.median(vals)), w, color=color[g], label=None if g in shown else g)
            ax.plot([at] * len(vals), vals, "k.", ms=4)
            shown.add(g)
    x = np.arange(len(systems))
    ax.axhline(1.2, color="k", lw=0.8, ls="--", label="goal: 1.2x")
    ax.set_yscale("log")
    ax.set_xticks(x, systems)
    ax.set_ylabel("sysid error / true-params error")
    ax.set_title("System identification against the true-parameter model", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "compare.png", dpi=110)
    plt.close(fig)
    return table


# -- main -----------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """This script's flags; ``build_parser().parse_args([])`` gives every default (``control_sysid``
    starts its training settings from them)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--sequences", type=int, nargs=3, default=(5000, 100, 200), metavar=("TRAIN", "VALID", "TEST"))
    ap.add_argument("--num-steps", type=int, default=100, help="steps per simulated sequence")
    ap.add_argument("--window", type=int, default=20, help="identification window (steps)")
    ap.add_argument("--seconds", type=float, default=120.0, help="training cap per model (wall clock)")
    ap.add_argument("--steps", type=int, default=20000, help="training steps per model (lr x0.6 every quarter)")
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--valid-every", type=int, default=1000)
    ap.add_argument("--latent", type=int, default=128)
    ap.add_argument("--edge-width", type=int, default=256)
    ap.add_argument("--node-width", type=int, default=128)
    ap.add_argument("--gid", type=int, default=10, help="G_ID width per node / edge / global (and GN_p's hidden)")
    ap.add_argument("--identifier-latent", type=int, default=128)
    ap.add_argument("--identifier-mlp", type=int, nargs="+", default=(128, 128))
    ap.add_argument("--probe-train", type=int, default=2000, help="train sequences the probe is fitted on")
    ap.add_argument("--fig9-sequences", type=int, default=50)
    ap.add_argument("--impl", default="warp", choices=("warp", "torch"))
    ap.add_argument("--backend", default="mujoco")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--data", default=None, help="dataset folder (cached; default: a temporary one)")
    ap.add_argument("--runs", default=None, help="checkpoint folder (default: a temporary one)")
    ap.add_argument("--out", default=None, help="default: bench/results/sysid_figures (--quick: a temporary folder)")
    ap.add_argument("--no-capture", action="store_true", help="run the training steps eagerly on CUDA too")
    ap.add_argument("--reference-runs", type=int, default=1,
                    help="true-parameter models trained identically; Figure 8's reference is their median")
    ap.add_argument("--precision", default=None, choices=("fp32", "tf32"),
                    help="the models' GEMM precision on CUDA (default: the library's, tf32)")
    ap.add_argument("--noise", type=float, default=None,
                    help="TrainConfig.noise_std of every model (default: the library's, 0.003)")
    ap.add_argument("--ema", type=float, default=0.0,
                    help="TrainConfig.ema of every model: validate and keep a moving average of the weights (default 0: off)")
    add_sysid_arguments(ap.add_argument_group("system identification (gnwarp train --sysid's flags)"))
    ap.add_argument("--label", default=None, help="a `run` label on every row written")
    ap.add_argument("--rebuild", action="store_true", help="only rebuild summary.md, fig8.png and probe.md from records.jsonl and results.jsonl")
    ap.add_argument("--compare", action="store_true",
                    help="only write compare.md / compare.png: the --label runs in results.jsonl side by side")
    ap.add_argument("--quick", action="store_true", help="tiny sizes on the CPU: a smoke test of the script")
    return ap


def main():
    args = build_parser().parse_args()
    args.valid, args.test = args.sequences[1], args.sequences[2]
    args.fig9_lengths, args.normalizer_warmup = FIG9_LENGTHS, 20
    if args.quick:
        args.sequences, args.num_steps, args.window, args.seconds, args.steps = (32, 4, 8), 24, 8, 5.0, 40
        args.valid, args.test, args.batch, args.valid_every, args.normalizer_warmup = 4, 8, 16, 1000, 2
        args.latent, args.edge_width, args.node_width = 16, 32, 16
        args.gid, args.identifier_latent, args.identifier_mlp = 6 if args.readout == "ridge" else 4, 16, (16,)
        args.probe_train, args.fig9_sequences, args.fig9_lengths = 32, 3, (0.4, 0.9)
        args.impl, args.device, args.backend = "torch", "cpu", "mujoco"
    sysid_config(args)   # a bad sysid flag is refused before any data is made
    out = experiment_out("sysid_figures", args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    if args.compare:
        path = out / "results.jsonl"
        if not path.is_file():
            raise SystemExit(f"--compare: {path} does not exist")
        print(compare_runs(out, [json.loads(line) for line in path.read_text().splitlines() if line.strip()]))
        return
    if args.rebuild:
        args.systems = ""
    from gnwarp import data
    from gnwarp.interop import resolve_device

    from gnwarp.eval.records import git_commit, write_records

    dev, commit = device_name(resolve_device(args.device)), git_commit()
    new = []
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(args.data or Path(tmp) / "data")
        runs = Path(args.runs or Path(tmp) / "runs")
        data_dir.mkdir(parents=True, exist_ok=True)
        for system in filter(None, args.systems.split(",")):
            t0 = time.perf_counter()
            path = data_dir / f"{system}-param-{'-'.join(map(str, args.sequences))}x{args.num_steps}-s{args.seed}.h5"
            if not path.exists():
                ds = data.generate(system, tuple(args.sequences), num_steps=args.num_steps, seed=args.seed,
                                   backend=args.backend, parameterized=True, progress=False)
                try:
                    ds.save(path)
                except FileExistsError:   # another run sharing --data wrote it meanwhile (saves are atomic)
                    pass
            ds = data.load(path, lazy=False)
            t_data = time.perf_counter() - t0
            models, info = train_all(args, ds, system, runs)
            rows = fig8_rows(args, system, ds, models)
            for r in (r for r in rows if "model" in r):   # the Figure 8 and oracle rows: their training
                key = "sysid" if r["model"].startswith("sysid") else r["model"]
                r.update(steps=info[key]["steps"], train_seconds=round(info[key]["seconds"], 1))
            rows += probe_rows(args, system, ds, models["sysid"])
            sysid, options = sysid_config(args)
            if options.param_loss > 0:
                rows += estimate_rows(args, system, ds, models["sysid"])
            rows += spread_rows(args, system, ds, models["sysid"])
            if system == "pendulum":
                rows += fig9(args, models, out)
            # the sysid settings trained with (each flag's value, its config's default where not set)
            flags = {**{k: getattr(sysid, k) for k in SYSID_MODEL_FLAGS}, **options.to_dict(),
                     "gid_globals": sysid.identifier.out_globals}
            for r in rows:
                r.update(device=dev, quick=args.quick, data_seconds=round(t_data, 1), **flags,
                         precision=args.precision or "tf32", noise_std=cfg_noise(args), ema=args.ema,
                         **({"run": args.label} if args.label else {}),
                         sequences=list(args.sequences), date=time.strftime("%Y-%m-%d %H:%M"))
                if r["part"] != "sequences":   # 7 x S numbers: in results.jsonl only
                    print(json.dumps(r), flush=True)
            new += rows
            with open(out / "results.jsonl", "a") as f:
                for r in rows:
                    f.write(json.dumps(r) + "\n")
            write_records(out / "records.jsonl", to_records(rows, commit=commit))
    from gnwarp.eval.records import read_records
    every = latest([json.loads(line) for line in (out / "results.jsonl").read_text().splitlines() if line.strip()])
    records = read_records(out / "records.jsonl")
    print(f"wrote {write_summary(out, records, args.quick)}")
    write_probe(out, every)
    plot_fig8(out, records)
    print(f"wrote {out}")

if __name__ == "__main__":
    main()

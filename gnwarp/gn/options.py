"""How a GN block runs, apart from what it computes: ``RunOptions`` (what users set), resolved once
per call into a ``ResolvedRun`` (dtypes, TF32, the fp16x3 rule) that every layer below reads.

The same weights give the same results, to rounding, under any options: options change the
implementation and the arithmetic, never the model. Checkpoints store the options a model was
trained with, and ``load_model(path, precision=...)`` overrides them without touching weights.
"""
from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from typing import Annotated, Literal, get_args

import torch

from gnwarp.validation import Allowed, ConfigError, Count, Flag, check_fields, check_keys
from gnwarp.gn.rules import TUNABLES
from gnwarp.interop import WP_DTYPE

__all__ = ["PRECISIONS", "IMPLS", "PATHS", "EDGE_FIRST_LAYERS", "RunOptions", "ResolvedRun", "tf32_matmul",
           "check_option_names", "ConfigError"]

Precision = Literal["fp32", "tf32", "fp16", "bf16", "fp16x3", "fp64"]
Impl = Literal["warp", "torch"]
PathName = Literal["auto", "blas", "tile"]
EdgeFirstLayer = Literal["auto", "concat", "project"]
EmulateMin = Annotated[tuple[Count, Count], Allowed("(rows, width), two integers >= 0")]
PRECISIONS, IMPLS, PATHS, EDGE_FIRST_LAYERS = (get_args(t) for t in (Precision, Impl, PathName, EdgeFirstLayer))
# names of earlier versions, still read from saved configs
_LEGACY_KEYS = {"backend": "impl"}
_LEGACY_VALUES = {"path": {"split": "blas"}, "edge_first_layer": {"split": "project"}}


@dataclass(frozen=True)
class RunOptions:
    """How a GN block runs (``GraphNetwork(options=...)``, ``ModelConfig.run``).

    Args:
        impl: "warp" (hand-written Warp kernels, the default) or "torch" (the pure-torch reference).
        path: Warp path: "blas" (Warp kernels for the graph work, BLAS GEMMs for the dense layers),
            "tile" (one fused Warp-tile kernel per update) or "auto" (``rules.choose_path``).
        precision: "fp32" (IEEE, in the parameters' dtype: float32 or float64), "fp64" (the same,
            with float64 parameters: models are cast to float64), "tf32" (float32 GEMMs on TF32
            tensor cores), "fp16" / "bf16" (GEMM inputs and activations in that dtype, sums in
            float32; outputs in the parameters' dtype), or "fp16x3" (float32-accurate GEMMs as
            three fp16 tensor-core products, for the MLPs ``emulate_min`` selects; IEEE fp32
            elsewhere, in the backward, and in the torch implementation).
        deterministic: aggregate with ordered segment sums (edges sorted by receiver) instead of
            atomics: bitwise identical results run to run, forward and backward.
        edge_first_layer: how the blas path computes the edge MLP's first layer: "concat" (the
            gathered rows [e, v_s, v_r, u] side by side, then one GEMM), "project" (node and
            global projections once per node / graph, gathered and added per edge) or "auto"
            (``rules.edge_concat``). Same numbers up to rounding.
        emulate_min: fp16x3's rule, (rows, hidden width): an MLP emulates from that many input
            rows and that hidden width; None takes ``TUNABLES``' measured rule.
        check_inputs: validate graphs before any launch (shapes, dtypes, devices, index ranges,
            finiteness). Costs a few host syncs; models, which build their own graphs, skip it.
    """
    impl: Impl = "warp"
    path: PathName = "auto"
    precision: Precision = "fp32"
    deterministic: Flag = False
    edge_first_layer: EdgeFirstLayer = "auto"
    emulate_min: EmulateMin | None = None
    check_inputs: Flag = True

    def __post_init__(self):
        check_fields(self)  # every value against its annotation: one ConfigError naming the key

    def replace(self, **changes) -> "RunOptions":
        """A copy with ``changes`` (validated)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["emulate_min"] = None if self.emulate_min is None else list(self.emulate_min)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RunOptions":
        """Options from a saved dict; names of earlier versions (``backend``, path / edge first
        layer "split") are read as today's; unknown keys raise ValueError."""
        if not isinstance(d, dict):
            check_keys(cls, d)
        d = {_LEGACY_KEYS.get(k, k): v for k, v in d.items()}
        for k, renames in _LEGACY_VALUES.items():
            if isinstance(d.get(k), str) and d[k] in renames:
                d[k] = renames[d[k]]
        return cls(**check_keys(cls, d, "run options"))

    @property
    def param_dtype(self) -> torch.dtype:
        """The parameter dtype these options ask a model for: float64 for "fp64", else float32."""
        return torch.float64 if self.precision == "fp64" else torch.float32

    def resolve(self, param_dtype: torch.dtype, device: torch.device | None = None) -> "ResolvedRun":
        """What these options mean for parameters of ``param_dtype`` (float32 or float64) on
        ``device``: off CUDA there is no TF32, and "tf32" runs exactly as "fp32"."""
        p = self.precision
        if p == "tf32" and device is not None and device.type != "cuda":
            p = "fp32"
        if param_dtype not in (torch.float32, torch.float64):
            raise TypeError(f"parameters must be float32 or float64, got {param_dtype}")
        if p == "fp64" and param_dtype != torch.float64:
            raise ValueError(f"precision='fp64' needs float64 parameters, got {param_dtype} (call .double())")
        half = {"fp16": torch.float16, "bf16": torch.bfloat16}.get(p)
        compute = half if half is not None else param_dtype
        emulate = None
        if p == "fp16x3" and param_dtype == torch.float32:
            emulate = self.emulate_min or (TUNABLES.emulate_min_rows, TUNABLES.emulate_min_width)
        return ResolvedRun(self, param_dtype, compute, torch.float64 if compute == torch.float64 else torch.float32,
                           tf32=p == "tf32", tensor_cores=p in ("tf32", "fp16", "bf16"), ieee=p in ("fp32", "fp64"),
                           emulate=emulate, autocast=half)


@dataclass(frozen=True)
class ResolvedRun:
    """``RunOptions`` resolved for one parameter dtype: built once per block call, passed down."""
    options: RunOptions
    param_dtype: torch.dtype
    compute_dtype: torch.dtype        # GEMM inputs and activations
    acc_dtype: torch.dtype            # scatter-sums, bias and input gradients
    tf32: bool                        # float32 GEMMs on TF32 tensor cores
    tensor_cores: bool                # every GEMM runs on tensor cores (tf32, fp16, bf16)
    ieee: bool                        # IEEE arithmetic in the parameters' dtype (fp32, fp64)
    emulate: tuple[int, int] | None   # fp16x3: (rows, hidden width) from which an MLP's GEMMs emulate
                                      # float32 on fp16 tensor cores (float32 parameters only)
    autocast: torch.dtype | None      # fp16 / bf16: the torch implementation's autocast dtype

    @property
    def impl(self) -> str:
        return self.options.impl

    @property
    def path(self) -> str:
        return self.options.path

    @property
    def precision(self) -> str:
        return self.options.precision

    @property
    def deterministic(self) -> bool:
        return self.options.deterministic

    @property
    def wp_dtype(self):
        return WP_DTYPE[self.compute_dtype]

    @property
    def wp_acc(self):
        return WP_DTYPE[self.acc_dtype]

    def matmul(self):
        """Context for this run's float32 GEMMs (TF32 for "tf32")."""
        return tf32_matmul(self.tf32)


def check_option_names(names, where: str) -> None:
    """Raise TypeError if any of ``names`` is not a ``RunOptions`` field."""
    bad = sorted(set(names) - set(RunOptions.__dataclass_fields__))
    if bad:
        raise TypeError(f"{where} got unknown run options {bad} (see gnwarp.RunOptions)")


@contextlib.contextmanager
def tf32_matmul(enabled: bool):
    """Scoped TF32 for float32 GEMMs when ``enabled``: torch's ``fp32_precision`` setting where it
    exists (torch >= 2.9; mixing it with the legacy ``allow_tf32`` flag makes torch raise), else
    the legacy ``allow_tf32`` flag (older torch raises AttributeError for ``fp32_precision``)."""
    if not enabled:
        yield
        return
    m = torch.backends.cuda.matmul
    name, value = ("fp32_precision", "tf32") if _has_fp32_precision(m) else ("allow_tf32", True)
    old = getattr(m, name)
    setattr(m, name, value)
    try:
        yield
    finally:
        setattr(m, name, old)


def _has_fp32_precision(matmul) -> bool:
    """Whether this torch has the ``fp32_precision`` TF32 setting (its absence raises AttributeError)."""
    try:
        getattr(matmul, "fp32_precision")
    except AttributeError:
        return False
    return True

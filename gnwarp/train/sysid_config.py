"""The training options of system identification (``SysIDTrainConfig``, saved in every
``SysIDTrainer`` checkpoint's config.json) and the ``--sysid`` command-line flags, generated from
the fields of ``SysIDConfig`` and ``SysIDTrainConfig`` (``add_sysid_arguments``,
``sysid_settings``), which ``gnwarp train --sysid`` and the bench scripts share."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated

from pydantic import Strict

from gnwarp.models.recurrent import RecurrentGNConfig
from gnwarp.models.sysid_config import SysIDConfig
from gnwarp.validation import (ConfigError, FloatRange, PositiveInt, add_config_flags, check_fields, check_keys,
                               config_flags_given, config_from_flags, described, flag_name)

__all__ = ["SysIDTrainConfig", "SYSID_MODEL_FLAGS", "add_sysid_arguments", "sysid_flags_given", "sysid_flag_values",
           "sysid_settings"]

# numbers only (a string such as "1" is refused, not read as one)
Share = Annotated[FloatRange(ge=0, le=1), Strict()]
Weight = Annotated[FloatRange(ge=0), Strict()]
Count = Annotated[PositiveInt, Strict()]

# the SysIDConfig fields a flag sets (the others: sizes and what the data fills in)
SYSID_MODEL_FLAGS = ("transitions", "stateless", "readout", "ridge_features", "ridge", "ridge_head", "local_params",
                     "nominal_static")


@dataclass
class SysIDTrainConfig:
    """What a ``SysIDTrainer`` adds to a ``TrainConfig`` (each default is the paper's training,
    Algorithm D.4); saved under "sysid_train" in every checkpoint's config.json.

    ``targets`` (beyond the paper's 1): one-step losses per identification window, at K different
    steps outside it, so that each identification (GN_p's whole window, most of a step's work) gets
    K times the signal. ``start_windows`` (beyond the paper's 0): the fraction of identification
    windows drawn at their sequence's start (s0 = 0) rather than uniformly: identification in use
    (``gnwarp evaluate``, Figure 8, ``control.identify_on_env``) reads an episode's first steps,
    which uniform windows reach once in T - W + 1 draws. ``consistency`` (beyond the paper's 0):
    the weight of a window-consistency term: each batch's sequences come in pairs, two independent
    windows of one sequence, and the loss adds ``consistency`` times the share of G_ID's variance
    over the batch that lies between the two windows of a pair (``window_spread``). ``param_loss``
    (beyond the paper's 0, which reads no labels): the weight of the mean squared error between
    G_ID's first P global columns and the instance's P parameters, standardized over the train
    split (``gnwarp.models.sysid_params.param_stats``). ``param_teacher`` (with ``param_loss``):
    the fraction of windows whose forward model reads the instance's true standardized parameters
    in those columns instead of GN_p's estimate (teacher forcing)."""
    targets: Count = described(1, "one-step losses per identification window (the paper's: 1)")
    start_windows: Share = described(0.0, "the fraction of identification windows at their sequence's start, where "
                                          "identification reads in use (0: uniform windows, the paper's)")
    consistency: Weight = described(0.0, "the weight of a window-consistency term: pairs of windows of one sequence "
                                         "should identify alike (0: the paper's; beyond the paper)")
    param_loss: Weight = described(0.0, "the weight of supervising G_ID's first global columns with the data's "
                                        "instance parameters (0: the paper's, no labels; beyond the paper)")
    param_teacher: Share = described(0.0, "with param_loss: the fraction of windows whose forward model reads the "
                                          "true parameters in G_ID's supervised columns (teacher forcing; 1: the "
                                          "forward model trains as a true-parameter model)")

    def __post_init__(self):
        check_fields(self)
        if self.param_teacher > 0 and self.param_loss == 0:
            raise ConfigError("param_teacher", "param_teacher hands the forward model the parameters param_loss "
                                               "supervises: it needs param_loss > 0")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SysIDTrainConfig":
        return cls(**check_keys(cls, d, "system-identification training keys"))

    @classmethod
    def from_checkpoint(cls, cfg: dict) -> "SysIDTrainConfig":
        """The options a checkpoint's config.json (``cfg``) records: its "sysid_train" table, or in
        a checkpoint written before that table, the keys its "train" table holds of these fields
        (the defaults, the paper's training, for those it lacks)."""
        if "sysid_train" in cfg:
            return cls.from_dict(cfg["sysid_train"])
        train = cfg.get("train") if isinstance(cfg.get("train"), dict) else {}
        return cls(**{f.name: train[f.name] for f in dataclasses.fields(cls) if f.name in train})


def add_sysid_arguments(parser) -> None:
    """System identification's options as flags on ``parser`` (a parser or an argument group):
    one per field of ``SysIDConfig`` in ``SYSID_MODEL_FLAGS`` and of ``SysIDTrainConfig``
    (``gnwarp.validation.add_config_flags``: its description, its default, its values checked),
    and ``--gid-globals`` (G_ID's and GN_p's hidden global width). ``sysid_settings`` reads them."""
    add_config_flags(parser, SysIDConfig, SYSID_MODEL_FLAGS)
    parser.add_argument("--gid-globals", type=int, default=None, metavar="G",
                        help="G_ID's global width, and GN_p's hidden globals (default: the identifier's, 10); with "
                             "param_loss at least the system's parameter count (cheetah 20, JACO 18; "
                             "RecurrentGNConfig.out_globals)")
    add_config_flags(parser, SysIDTrainConfig)


def sysid_flags_given(args) -> list[str]:
    """The flags of ``add_sysid_arguments`` set in ``args``."""
    given = [*config_flags_given(args, SysIDConfig, SYSID_MODEL_FLAGS), *config_flags_given(args, SysIDTrainConfig)]
    return [flag_name(k) for k in given] + (["--gid-globals"] if args.gid_globals is not None else [])


def sysid_flag_values(args) -> dict:
    """{name: value} of every flag of ``add_sysid_arguments`` in ``args`` (None: not set, the
    config's default); what a run records."""
    names = (*SYSID_MODEL_FLAGS, "gid_globals", *(f.name for f in dataclasses.fields(SysIDTrainConfig)))
    return {k: getattr(args, k) for k in names}


def sysid_settings(args, identifier: RecurrentGNConfig | None = None, **config) -> tuple[SysIDConfig, SysIDTrainConfig]:
    """(``SysIDConfig``, ``SysIDTrainConfig``) from ``add_sysid_arguments``' flags in ``args``;
    ``identifier``: GN_p's sizes before ``--gid-globals`` (default ``SysIDConfig``'s);
    ``config``: further ``SysIDConfig`` fields (``window``). A refused value raises
    ``ConfigError`` naming its flag."""
    identifier = identifier if identifier is not None else SysIDConfig().identifier
    if args.gid_globals is not None:   # G_ID's global width (and GN_p's hidden globals)
        try:
            identifier = dataclasses.replace(identifier, hidden_globals=args.gid_globals, out_globals=args.gid_globals)
        except ConfigError as e:
            raise ConfigError("--gid-globals", e.reason) from None
    sysid = config_from_flags(SysIDConfig, args, SYSID_MODEL_FLAGS, identifier=identifier, **config)
    return sysid, config_from_flags(SysIDTrainConfig, args)

"""Training of forward models (D.7, D.8): ``Trainer`` / ``train``, ``TrainConfig``, the checkpoint
format (``save_checkpoint``, ``load_model``), the batch sampler, ``FlatAdam`` and ``WeightAverage``;
system identification trained end to end (``SysIDTrainer``, ``SysIDTrainConfig``, D.7.2); the recurrent
one-step model trained with teacher forcing (``TeacherForcingTrainer``, D.7.3)."""
from gnwarp.train.checkpoint import CheckpointError, load_checkpoint, load_model, save_checkpoint
from gnwarp.train.config import SCHEDULES, TrainConfig
from gnwarp.train.optim import FlatAdam, WeightAverage
from gnwarp.train.sampler import BatchSampler
from gnwarp.train.trainer import Trainer, train
from gnwarp.train.sysid import SysIDTrainer, load_sysid
from gnwarp.train.sysid_config import SysIDTrainConfig
from gnwarp.train.recurrent import TeacherForcingTrainer, load_recurrent, train_teacher_forcing

__all__ = ["Trainer", "train", "TrainConfig", "SCHEDULES", "save_checkpoint", "load_model",
           "load_checkpoint", "CheckpointError", "FlatAdam", "WeightAverage", "BatchSampler",
           "SysIDTrainer", "SysIDTrainConfig", "load_sysid", "TeacherForcingTrainer", "load_recurrent",
           "train_teacher_forcing"]

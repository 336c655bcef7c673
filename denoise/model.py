"""`N2VModel`: a trained UNet with its intensity normalisation, and checkpoints.

The network works on normalised intensities ``(x - mean) / std`` (per channel,
statistics of the training images) and predicts a residual:
``out = x_in + alpha * UNet(x_in)`` in normalised units (``alpha = 0.5``).
"""

from __future__ import annotations

import dataclasses
import io
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from denoise.training_restart import TrainingRestart
from denoise.unet import UNet, UNetConfig
from mvgeo.common.atomic import atomic_write_bytes
from mvgeo.common.errors import InputError, check_shape

CHECKPOINT_FORMAT = "denoise-gs/n2v-unet/1"


@dataclass
class N2VModel:
    """A UNet plus what is needed to apply it to ``[0, 1]`` images.

    Attributes:
        unet: the network (float32).
        mean: per-channel mean of the training images, ``[0, 1]`` units.
        std: per-channel standard deviation (floored at `STD_FLOOR`).
        alpha: residual scale.
        mask_prob, replacement, radius: the training masking, reused by K-pass inference.
        history: training losses, one per step (round 1, then round 2 appended).
        restarts: the trainings `denoise.n2v.optimise_unet` abandoned as diverging and started again, in
            order (not saved in checkpoints: they describe one training, not the weights).
        blind_spot: the network was trained blind-spot only (round 1), so inference may
            fuse its prediction with the ignored centre pixel (`denoise.fusion`); round 2
            trains on the full input and clears it.
    """

    unet: UNet
    mean: tuple[float, ...]
    std: tuple[float, ...]
    alpha: float = 0.5
    mask_prob: float = 0.04
    replacement: str = "permute"
    radius: int = 5
    history: list[float] = field(default_factory=list)
    blind_spot: bool = True
    restarts: list[TrainingRestart] = field(default_factory=list)

    STD_FLOOR = 1e-2

    @property
    def unet_config(self) -> UNetConfig:
        return self.unet.config

    def apply(self, x: Tensor, *, unet: torch.nn.Module | None = None) -> Tensor:
        """Run the residual network on a (possibly masked) batch.

        Args:
            x: ``[B, C, H, W]`` in ``[0, 1]`` units (float32).
            unet: another module with this model's weights (a training replica, `denoise.n2v`); default
                ``self.unet``.

        Returns:
            ``[B, C, H, W]`` in ``[0, 1]`` units (not clipped).
        """
        check_shape(x, ["B", len(self.mean), "H", "W"], "x")
        mean = torch.tensor(self.mean, dtype=x.dtype, device=x.device).reshape(1, -1, 1, 1)
        std = torch.tensor(self.std, dtype=x.dtype, device=x.device).reshape(1, -1, 1, 1)
        xn = (x - mean) / std
        return (xn + self.alpha * (self.unet if unet is None else unet)(xn)) * std + mean


def save_checkpoint(path: str | Path, model: N2VModel) -> None:
    """Write `model` to `path` atomically (a torch file with weights and config only)."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "unet_config": dataclasses.asdict(model.unet_config),
        "state_dict": {k: v.detach().cpu() for k, v in model.unet.state_dict().items()},
        "mean": list(model.mean),
        "std": list(model.std),
        "alpha": float(model.alpha),
        "masking": {"mask_prob": float(model.mask_prob), "replacement": model.replacement,
                    "radius": int(model.radius)},
        "history": [float(v) for v in model.history],
        "blind_spot": bool(model.blind_spot),
    }
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | Path, *, device: torch.device | str = "cpu") -> N2VModel:
    """Read a checkpoint written by `save_checkpoint` (``weights_only`` loading: no code runs).

    Raises:
        InputError: missing, corrupt or foreign file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint file does not exist", path=path, fix="pass the model.pt written by `denoise n2v`")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt files
        raise InputError(f"cannot read checkpoint ({type(exc).__name__})", path=path,
                         fix="re-create it with `denoise n2v`") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise InputError("not a denoise N2V checkpoint", path=path, fix="pass the model.pt written by `denoise n2v`")
    try:
        unet = UNet(UNetConfig(**state["unet_config"]))
        unet.load_state_dict(state["state_dict"])
    except (TypeError, KeyError, RuntimeError) as exc:
        raise InputError(f"checkpoint does not match this version's UNet: {exc}", path=path,
                         fix="re-create it with `denoise n2v`") from exc
    unet.to(device).eval()
    masking = state.get("masking", {})
    return N2VModel(unet=unet, mean=tuple(state["mean"]), std=tuple(state["std"]), alpha=float(state["alpha"]),
                    mask_prob=float(masking.get("mask_prob", 0.04)),
                    replacement=str(masking.get("replacement", "permute")), radius=int(masking.get("radius", 5)),
                    history=list(state.get("history", [])), blind_spot=bool(state.get("blind_spot", True)))

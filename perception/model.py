"""The network: an FCGF-style residual sparse U-Net and the paper's per-voxel head (Sec. 3.1-3.2).

The backbone follows FCGF's ResUNetBN2C (channels 32/64/128/256, transposed 64/64/64/128, a 7^3
first convolution); ``NetworkConfig`` can slim it, which docs/DESIGN.md section 9 invites where the
validation metrics hold. The head is three linear layers mapping each voxel's features to five
numbers: the existence logit, the residual centre (x, y, z, in ``LENGTH_UNIT``s) and the
orientation value.
"""

from __future__ import annotations

import copy
import weakref

import torch
from torch import nn

from perception.calibration import UNCALIBRATED
from perception.network import INFERENCE_ZOOM, NORM_AFTER, NetworkConfig
from perception.sparse import (SparseBatchNorm, SparseConv3d, SparseConvTranspose3d, SparseReLU, SparseTensor,
                               SubmanifoldConv3d, sparse_cat)


class ResBlock(nn.Module):
    """Two 3^3 submanifold convolutions with batch norm and an identity shortcut (FCGF's BasicBlock)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = SubmanifoldConv3d(channels, channels, 3)
        self.norm1 = SparseBatchNorm(channels)
        self.conv2 = SubmanifoldConv3d(channels, channels, 3)
        self.norm2 = SparseBatchNorm(channels)
        self.relu = SparseReLU(inplace=True)

    def forward(self, x: SparseTensor) -> SparseTensor:
        out = self.relu(self.norm1(self.conv1(x)))
        out = self.norm2(self.conv2(out))
        return out.replace_features(torch.relu_(out.features + x.features))


def _down(in_ch: int, out_ch: int) -> nn.ModuleDict:
    return nn.ModuleDict({"conv": SparseConv3d(in_ch, out_ch, 3, stride=2), "norm": SparseBatchNorm(out_ch),
                          "block": ResBlock(out_ch)})


def _up(in_ch: int, out_ch: int) -> nn.ModuleDict:
    return nn.ModuleDict({"conv": SparseConvTranspose3d(in_ch, out_ch, 3, stride=2),
                          "norm": SparseBatchNorm(out_ch), "block": ResBlock(out_ch)})


class MushroomNet(nn.Module):
    """Sparse U-Net backbone + per-voxel head; geometry only (``voxel_features``), never colour."""

    def __init__(self, config: NetworkConfig = NetworkConfig(), point_spacing: float | None = None,
                 inference_zoom: float = INFERENCE_ZOOM):
        super().__init__()
        self.config = config
        self.point_spacing = point_spacing
        """Point spacing of the beds it was trained on: inference thins denser clouds to it."""
        self.inference_zoom = inference_zoom
        """Scale at which inference reads clouds (``perception.detect.predict``), chosen per model."""
        self.calibration = UNCALIBRATED
        """What its cap scores and rim diameters mean (``perception.calibration``), from its weights file."""
        c1, c2, c3, c4 = config.channels
        u1, u2, u3, u4 = config.up_channels
        self.relu = SparseReLU(inplace=True)
        self.conv1 = SubmanifoldConv3d(config.in_channels, c1, config.first_kernel)
        self.norm1 = SparseBatchNorm(c1)
        self.block1 = ResBlock(c1)
        self.down2, self.down3, self.down4 = _down(c1, c2), _down(c2, c3), _down(c3, c4)
        self.up4 = _up(c4, u4)
        self.up3 = _up(c3 + u4, u3)
        self.up2 = _up(c2 + u3, u2)
        self.conv1_tr = SubmanifoldConv3d(c1 + u2, u1, 1)
        h1, h2 = config.head_hidden
        self.head = nn.Sequential(nn.Linear(u1, h1), nn.ReLU(), nn.Dropout(config.dropout),
                                  nn.Linear(h1, h2), nn.ReLU(), nn.Dropout(config.dropout), nn.Linear(h2, config.out_channels))

    def _step_down(self, stage: nn.ModuleDict, x: SparseTensor) -> SparseTensor:
        return stage["block"](self.relu(stage["norm"](stage["conv"](x))))

    def _step_up(self, stage: nn.ModuleDict, x: SparseTensor, target: SparseTensor) -> SparseTensor:
        return stage["block"](self.relu(stage["norm"](stage["conv"](x, target))))

    def forward(self, x: SparseTensor) -> torch.Tensor:
        """(V, out_channels) raw outputs per input voxel: existence logit, residual (LENGTH_UNITs; the centre
        with ``explicit-centre``), orientation value (the axis, 3, with ``explicit-orientation``)."""
        return self.head(self.features(x))

    def features(self, x: SparseTensor) -> torch.Tensor:
        """(V, up_channels[0]) per-voxel features the head reads: the backbone's last layer."""
        s1 = self.block1(self.relu(self.norm1(self.conv1(x))))
        s2 = self._step_down(self.down2, s1)
        s4 = self._step_down(self.down3, s2)
        s8 = self._step_down(self.down4, s4)
        up = self._step_up(self.up4, s8, s4)
        up = self._step_up(self.up3, sparse_cat(s4, up), s2)
        up = self._step_up(self.up2, sparse_cat(s2, up), s1)
        return self.relu(self.conv1_tr(sparse_cat(s1, up))).features




def fold_batch_norms(model: MushroomNet) -> MushroomNet:
    """An inference copy of ``model`` with every batch norm folded into the convolution before it.

    In eval mode a batch norm is a per-channel scale and shift, so it moves into the convolution's
    weights and a bias, which the convolution adds within its first product: a forward pass then
    skips a pass over the features and an allocation per batch norm (21 of them)."""
    folded = copy.deepcopy(model).eval()
    with torch.no_grad():
        for module in list(folded.modules()):
            for conv_name, norm_name in NORM_AFTER.items():
                conv, norm = getattr(module, conv_name, None), getattr(module, norm_name, None)
                if not isinstance(norm, SparseBatchNorm):
                    continue
                scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
                shift = norm.bias - norm.running_mean * scale
                if conv.bias is not None:
                    shift = shift + conv.bias * scale
                conv.weight.mul_(scale)
                conv.bias = nn.Parameter(shift)
                setattr(module, norm_name, nn.Identity())
    return folded


_folded_models: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""Per model, its state when folded and the folded copy."""


def inference_model(model: MushroomNet) -> MushroomNet:
    """``fold_batch_norms(model)``, folded again only when a weight or statistic of ``model`` has changed
    or moved since (training validates the model it is training)."""
    versions = tuple((tensor.data_ptr(), tensor._version) for tensor in model.state_dict(keep_vars=True).values())
    cached = _folded_models.get(model)
    if cached is None or cached[0] != versions:
        cached = _folded_models[model] = (versions, fold_batch_norms(model))
    return cached[1]


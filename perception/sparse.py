"""Sparse 3D convolution in plain PyTorch (docs/DESIGN.md section 9).

Voxels are rows of a ``SparseTensor``: features (N, C) and integer coords (N, 4) = (batch, x, y, z)
at the tensor's own level (stride 2^k holds floor(original / 2^k)). Neighbours are found in a dense
table of rows over the voxels' bounding box, where a voxel's index plus a constant is its neighbour's;
boxes too large for that (stray far points) pack coords into one int64 key, sort once and call
``torch.searchsorted``. A kernel map holds, per
kernel offset, the (input row, output row) pairs it connects; a convolution is, per offset,
gather -> matmul -> ``index_add_``. Maps are kept in a cache shared by all tensors derived from one
input, so each is built once per forward pass. Downsampling is Minkowski-style: the output voxels are
the occupied parent voxels, and the transposed conv runs the same map backwards. Only standard torch
ops are used, so everything runs on the device of the inputs. Training runs these; a trained network
runs in numpy (``perception.inference``, the same maps and layers), so commands start without torch.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from perception.inference import BATCH_MAX, COORD_BITS, COORD_MAX, COORD_MIN, DENSE_TABLE_CELLS, TABLE_MARGIN
from perception.inference import kernel_offsets as numpy_kernel_offsets
from perception.inference import pack as pack_keys  # array-generic: the same keys for torch tensors

KernelMap = list[tuple[torch.Tensor | None, torch.Tensor | None]]
"""Per kernel offset, (in_idx, out_idx) int64 rows it connects; (None, None) means the identity."""


class SparseTensor:
    """Features on occupied voxels; ``cache`` holds kernel maps shared with tensors derived from it."""

    __slots__ = ("features", "coords", "stride", "cache")

    def __init__(self, features: torch.Tensor, coords: torch.Tensor, stride: int = 1,
                 cache: dict | None = None):
        if features.dim() != 2 or coords.shape != (features.shape[0], 4):
            raise ValueError(f"need features (N, C) and coords (N, 4); got {tuple(features.shape)} "
                             f"and {tuple(coords.shape)}")
        if coords.dtype != torch.int64:
            raise ValueError(f"coords must be int64, got {coords.dtype}")
        self.features, self.coords, self.stride = features, coords, stride
        self.cache = {} if cache is None else cache

    def replace_features(self, features: torch.Tensor) -> SparseTensor:
        """The same voxels (and cache) with new features."""
        return SparseTensor(features, self.coords, self.stride, self.cache)

    def __repr__(self) -> str:
        return f"SparseTensor(n={len(self.coords)}, channels={self.features.shape[1]}, stride={self.stride})"


def pack(coords: torch.Tensor) -> torch.Tensor:
    """One int64 key per (b, x, y, z) row, ordered by batch then x, y, z; ValueError if unpackable."""
    batch, xyz = coords[:, 0], coords[:, 1:]
    if len(coords) and not (batch.min() >= 0 and batch.max() <= BATCH_MAX
                            and xyz.min() >= COORD_MIN and xyz.max() <= COORD_MAX):
        raise ValueError(f"coords out of the packable range: batch must lie in [0, {BATCH_MAX}] "
                         f"and x, y, z in [{COORD_MIN}, {COORD_MAX}]; got batch in "
                         f"[{int(batch.min())}, {int(batch.max())}], x, y, z in "
                         f"[{int(xyz.min())}, {int(xyz.max())}]")
    return pack_keys(coords)


def unpack(key: torch.Tensor) -> torch.Tensor:
    """Inverse of ``pack``: (N,) keys -> (N, 4) coords."""
    mask, bias = (1 << COORD_BITS) - 1, 1 << (COORD_BITS - 1)
    xyz = [((key >> s) & mask) - bias for s in (2 * COORD_BITS, COORD_BITS, 0)]
    return torch.stack([key >> (3 * COORD_BITS), *xyz], 1)


def kernel_offsets(kernel_size: int, centred: bool, device: torch.device | None = None) -> torch.Tensor:
    """(K, 3) offsets, x slowest and z fastest (spconv's weight order); {-r..r}^3 or {0..k-1}^3."""
    return torch.from_numpy(numpy_kernel_offsets(kernel_size, centred)).to(device)


def _key_deltas(offsets: torch.Tensor) -> torch.Tensor:
    """key(c + d) - key(c) for each offset d (exact while every field stays in range: see COORD_MARGIN)."""
    return pack_keys(torch.cat([torch.zeros_like(offsets[:, :1]), offsets], 1)) - pack_keys(offsets.new_zeros(4))


def _sorted_keys(x: SparseTensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted keys of ``x``'s voxels and the row of each, cached per stride."""
    entry = x.cache.get(("keys", x.stride))
    if entry is None:
        entry = x.cache[("keys", x.stride)] = torch.sort(pack(x.coords))
    return entry


def _dense_table(voxels: SparseTensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """(rows over the padded box, its lowest and highest cell, its strides), cached per stride; None
    when the box is too big."""
    key = ("table", voxels.stride)
    if key not in voxels.cache:
        coords = voxels.coords
        margin = torch.tensor([0, TABLE_MARGIN, TABLE_MARGIN, TABLE_MARGIN], device=coords.device)
        low, high = coords.min(0).values - margin, coords.max(0).values + margin
        extent = high + 1 - low
        if float(torch.prod(extent.double())) > DENSE_TABLE_CELLS:
            voxels.cache[key] = None
        else:
            strides = torch.tensor([int(torch.prod(extent[i + 1:])) for i in range(4)], device=coords.device)
            rows = torch.full((int(torch.prod(extent)),), -1, dtype=torch.int64, device=coords.device)
            rows[((coords - low) * strides).sum(1)] = torch.arange(len(coords), device=coords.device)
            voxels.cache[key] = (rows, low, high, strides)
    return voxels.cache[key]


def _lookup(voxels: SparseTensor, coords: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """(K, M): the row of ``voxels`` holding voxel coords[m] + offsets[k], or -1 where that voxel is empty."""
    if not len(voxels.coords) or not len(offsets) or not len(coords):
        return torch.full((len(offsets), len(coords)), -1, dtype=torch.int64, device=coords.device)
    dense = _dense_table(voxels)
    if dense is not None:
        rows, low, high, strides = dense
        reach = torch.cat([offsets.new_zeros(len(offsets), 1), offsets], 1)
        if bool((coords.min(0).values + reach.min(0).values >= low).all()
                and (coords.max(0).values + reach.max(0).values <= high).all()):
            return rows[((coords - low) * strides).sum(1)[None] + (reach * strides).sum(1)[:, None]]
    sorted_keys, order = _sorted_keys(voxels)
    keys = pack(coords)[None] + _key_deltas(offsets)[:, None]
    pos = torch.searchsorted(sorted_keys, keys).clamp_(max=len(sorted_keys) - 1)
    return torch.where(sorted_keys[pos] == keys, order[pos], torch.full_like(keys, -1))


def _pairs(found: torch.Tensor) -> KernelMap:
    """(K, M) rows of the input found for output m at offset k -> one (in_idx, out_idx) per offset.

    One ``nonzero`` over all offsets, split per offset: the pairs come out in the same order as from
    one call per offset, for a few calls instead of two per offset."""
    hit = found >= 0
    counts = hit.sum(1).tolist()
    out_idx = torch.nonzero(hit)[:, 1].split(counts)
    in_idx = found[hit].split(counts)
    return list(zip(in_idx, out_idx))


def submanifold_map(x: SparseTensor, kernel_size: int) -> KernelMap:
    """Output voxel o gathers input voxel o + d for every offset d of a centred cube.

    Offsets are ordered so that offset K-1-k is -d; its pairs are those of d swapped, so only the
    first half is searched.
    """
    key = ("subm", x.stride, kernel_size)
    if key not in x.cache:
        offsets = kernel_offsets(kernel_size, True, x.coords.device)
        kmap = _pairs(_lookup(x, x.coords, offsets[:len(offsets) // 2]))
        x.cache[key] = kmap + [(None, None)] + [(o, i) for i, o in reversed(kmap)]
    return x.cache[key]


def parent_coords(x: SparseTensor) -> torch.Tensor:
    """The occupied parent voxels unique(floor(coords / 2)) per batch, sorted, cached per stride."""
    key = ("coords", 2 * x.stride)
    if key not in x.cache:
        parents = x.coords.clone()
        parents[:, 1:] = torch.div(parents[:, 1:], 2, rounding_mode="floor")
        x.cache[key] = unpack(torch.unique(pack(parents)))
    return x.cache[key]


def downsample_map(fine: SparseTensor, kernel_size: int, coarse: torch.Tensor | None = None) -> KernelMap:
    """Coarse voxel o gathers fine voxels 2 o + d, d in {0,1}^3 (k=2) or {-1,0,1}^3 (k=3).

    ``coarse`` defaults to the parents of ``fine``; the map is cached on ``fine`` with its size.
    """
    if kernel_size not in (2, 3):
        raise ValueError(f"stride-2 kernels must have size 2 or 3, got {kernel_size}")
    key = ("down", fine.stride, kernel_size)
    if key not in fine.cache:
        coarse = parent_coords(fine) if coarse is None else coarse
        offsets = kernel_offsets(kernel_size, kernel_size == 3, coarse.device)
        doubled = torch.cat([coarse[:, :1], 2 * coarse[:, 1:]], 1)
        fine.cache[key] = (_pairs(_lookup(fine, doubled, offsets)), len(coarse))
    return fine.cache[key][0]


class _SparseConvFunction(torch.autograd.Function):
    """out[o] += features[i] @ weight[k] for every pair (i, o) of offset k.

    Saves only ``features`` and ``weight``; backward gathers again instead of keeping the per-offset
    gathered copies, which would cost K times the input's memory. Rows are gathered with
    ``index_select``, faster than indexing on CPU; one gather-multiply-scatter per offset beats an
    im2col table, a CSR matmul and a single scatter over all offsets on beds' sparse voxels (about 8 of
    27 neighbours occupied; docs/DESIGN.md section 9).
    """

    @staticmethod
    def forward(ctx, features: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, kmap: KernelMap,
                n_out: int):
        weights = weight.unbind(0)
        # the sum starts at a submanifold map's identity offset, plus the bias, or at the bias alone:
        # no pass to zero the output, none to add the bias
        identity = next((k for k, (i, _) in enumerate(kmap) if i is None), None)
        if identity is not None:
            out = features @ weights[identity] if bias is None else torch.addmm(bias, features, weights[identity])
        else:
            out = features.new_zeros(n_out, weight.shape[2]) if bias is None else bias.expand(n_out, -1).clone()
        for k, (i, o) in enumerate(kmap):
            if i is not None and len(i):
                out.index_add_(0, o, features.index_select(0, i) @ weights[k])
        ctx.save_for_backward(features, weight)
        ctx.kmap = kmap
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        features, weight = ctx.saved_tensors
        need_f, need_w, need_b = ctx.needs_input_grad[:3]
        grad_f = torch.zeros_like(features) if need_f else None
        grad_w = torch.zeros_like(weight) if need_w else None
        for k, (i, o) in enumerate(ctx.kmap):
            if i is not None and not len(i):
                continue
            g = grad_out if o is None else grad_out.index_select(0, o)
            if need_w:
                grad_w[k] = (features if i is None else features.index_select(0, i)).T @ g
            if need_f:
                if i is None:
                    grad_f += g @ weight[k].T
                else:
                    grad_f.index_add_(0, i, g @ weight[k].T)
        return grad_f, grad_w, grad_out.sum(0) if need_b else None, None, None


def sparse_conv(features: torch.Tensor, weight: torch.Tensor, kmap: KernelMap, n_out: int,
                bias: torch.Tensor | None = None) -> torch.Tensor:
    """Apply ``weight`` (K, C_in, C_out) along kernel map ``kmap``, plus ``bias`` (C_out); returns (n_out, C_out)."""
    return _SparseConvFunction.apply(features, weight, bias, kmap, n_out)


def transpose_map(kmap: KernelMap) -> KernelMap:
    """The same pairs run from output to input (what a transposed conv needs)."""
    return [(o, i) for i, o in kmap]


class _SparseConvBase(nn.Module):
    """Weight (K, in_ch, out_ch), He-normal with fan_in = K * in_ch; optional bias."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int, bias: bool):
        super().__init__()
        self.in_ch, self.out_ch, self.kernel_size = in_ch, out_ch, kernel_size
        volume = kernel_size ** 3
        self.weight = nn.Parameter(torch.randn(volume, in_ch, out_ch) * math.sqrt(2.0 / (volume * in_ch)))
        self.bias = nn.Parameter(torch.zeros(out_ch)) if bias else None

    def extra_repr(self) -> str:
        return f"{self.in_ch}, {self.out_ch}, kernel_size={self.kernel_size}, bias={self.bias is not None}"


class SubmanifoldConv3d(_SparseConvBase):
    """Convolution whose output voxels are its input voxels (odd kernel sizes); He-initialised."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int = 3, bias: bool = False):
        if kernel_size % 2 == 0 or kernel_size < 1:
            raise ValueError(f"submanifold kernels must have an odd size, got {kernel_size}")
        super().__init__(in_ch, out_ch, kernel_size, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        if self.kernel_size == 1:
            weight = self.weight[0]
            return x.replace_features(x.features @ weight if self.bias is None
                                      else torch.addmm(self.bias, x.features, weight))
        out = sparse_conv(x.features, self.weight, submanifold_map(x, self.kernel_size), len(x.coords), self.bias)
        return x.replace_features(out)


class SparseConv3d(_SparseConvBase):
    """Stride-2 convolution onto the occupied parent voxels (Minkowski-style downsampling)."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int = 3, stride: int = 2, bias: bool = False):
        if stride != 2 or kernel_size not in (2, 3):
            raise ValueError(f"only stride 2 with kernel size 2 or 3 is supported, got "
                             f"stride {stride}, kernel size {kernel_size}")
        super().__init__(in_ch, out_ch, kernel_size, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        coarse = parent_coords(x)
        out = sparse_conv(x.features, self.weight, downsample_map(x, self.kernel_size), len(coarse), self.bias)
        return SparseTensor(out, coarse, 2 * x.stride, x.cache)


class SparseConvTranspose3d(_SparseConvBase):
    """Stride-2 upsampling onto the voxels of ``target``: the matching ``SparseConv3d`` map, reversed."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int = 3, stride: int = 2, bias: bool = False):
        if stride != 2 or kernel_size not in (2, 3):
            raise ValueError(f"only stride 2 with kernel size 2 or 3 is supported, got "
                             f"stride {stride}, kernel size {kernel_size}")
        super().__init__(in_ch, out_ch, kernel_size, bias)

    def forward(self, x: SparseTensor, target: SparseTensor) -> SparseTensor:
        if x.stride != 2 * target.stride:
            raise ValueError(f"target stride must be half the input's: {target.stride} vs {x.stride}")
        fine = target if x.cache is target.cache else SparseTensor(target.features, target.coords, target.stride)
        kmap = downsample_map(fine, self.kernel_size, x.coords)
        if fine.cache[("down", fine.stride, self.kernel_size)][1] != len(x.coords):
            raise ValueError("x is not the downsampling of target: its voxel count differs from the map's")
        out = sparse_conv(x.features, self.weight, transpose_map(kmap), len(target.coords), self.bias)
        return target.replace_features(out)


class SparseBatchNorm(nn.BatchNorm1d):
    """BatchNorm1d over all voxels of the batch."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_features(super().forward(x.features))


class SparseReLU(nn.ReLU):
    """ReLU on the features; ``inplace=True`` where they are a fresh output nothing else reads."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_features(super().forward(x.features))


def sparse_cat(a: SparseTensor, b: SparseTensor) -> SparseTensor:
    """Concatenate the channels of two tensors on the same voxels (U-Net skip connections)."""
    if a.stride != b.stride or not (a.coords is b.coords or torch.equal(a.coords, b.coords)):
        raise ValueError(f"sparse_cat needs the same voxels: {a} vs {b}")
    return a.replace_features(torch.cat([a.features, b.features], 1))

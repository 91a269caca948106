"""perception.sparse against spconv 2.3.8 (one thread, where its CPU path is correct), plus gradcheck."""

import numpy as np
import pytest
import torch

from perception.sparse import (COORD_MAX, COORD_MIN, SparseConv3d, SparseConvTranspose3d, SparseTensor,
                               SubmanifoldConv3d, downsample_map, pack, sparse_cat, sparse_conv,
                               submanifold_map, transpose_map)

spc = pytest.importorskip("spconv.pytorch")
spconv_ops = pytest.importorskip("spconv.pytorch.ops")

GRID = 24
IN_CH, OUT_CH = 4, 5
FWD = dict(rtol=1e-5, atol=1e-5)
GRAD = dict(rtol=1e-4, atol=1e-4)


@pytest.fixture(autouse=True)
def one_thread(monkeypatch):
    """spconv's CPU scatter-add races with several threads, and its backward asks for a CUDA stream."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    monkeypatch.setattr(spconv_ops, "get_current_stream", lambda: 0)
    yield
    torch.set_num_threads(threads)


def random_coords(n: int, seed: int, grid: int = GRID) -> torch.Tensor:
    """About n unique (b, x, y, z) in two batches of a grid^3 box, in random row order."""
    g = torch.Generator().manual_seed(seed)
    raw = torch.cat([torch.randint(0, 2, (n, 1), generator=g), torch.randint(0, grid, (n, 3), generator=g)], 1)
    coords = torch.unique(raw, dim=0)
    return coords[torch.randperm(len(coords), generator=g)]


def spconv_weight(w: torch.Tensor) -> torch.Tensor:
    """Ours (K, in, out), x-offset slowest -> spconv's (out, kx, ky, kz, in)."""
    k = round(w.shape[0] ** (1 / 3))
    return w.permute(2, 0, 1).reshape(w.shape[2], k, k, k, w.shape[1]).contiguous()


def spconv_input(features: torch.Tensor, coords: torch.Tensor) -> "spc.SparseConvTensor":
    return spc.SparseConvTensor(features, coords.int(), [GRID] * 3, 2)


def rows_of(queries: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Row of ``table`` holding each row of ``queries`` (all must be present)."""
    where = {tuple(c): i for i, c in enumerate(table.tolist())}
    return torch.tensor([where[tuple(c)] for c in queries.tolist()])


def leaf(t: torch.Tensor) -> torch.Tensor:
    return t.detach().clone().requires_grad_(True)


@pytest.mark.parametrize("kernel_size", [3, 5, 7])
def test_submanifold_matches_spconv(kernel_size):
    coords = random_coords(3000, seed=kernel_size)
    feats = torch.randn(len(coords), IN_CH)
    ours = SubmanifoldConv3d(IN_CH, OUT_CH, kernel_size)
    ref = spc.SubMConv3d(IN_CH, OUT_CH, kernel_size, bias=False)
    ref.weight.data.copy_(spconv_weight(ours.weight.data))

    f_ours, f_ref = leaf(feats), leaf(feats)
    y = ours(SparseTensor(f_ours, coords))
    r = ref(spconv_input(f_ref, coords))
    assert torch.equal(r.indices.long(), coords)
    torch.testing.assert_close(y.features, r.features, **FWD)

    grad_out = torch.randn_like(y.features)
    y.features.backward(grad_out)
    r.features.backward(grad_out)
    torch.testing.assert_close(f_ours.grad, f_ref.grad, **GRAD)
    torch.testing.assert_close(spconv_weight(ours.weight.grad), ref.weight.grad, **GRAD)


@pytest.mark.parametrize("kernel_size", [2, 3])
def test_strided_and_transposed_match_spconv(kernel_size):
    """Down: spconv output u gathers input 2u - padding + k, ours o gathers 2o + d; with d = k - padding
    these are the same sums, so compare at equal coords. Ours outputs only the occupied parents
    floor(c / 2); spconv (kernel 3, padding 1) also outputs (c + 1) / 2 for odd c, a superset."""
    padding = (kernel_size - 1) // 2
    coords = random_coords(3000, seed=10 + kernel_size)
    feats = torch.randn(len(coords), IN_CH)
    down = SparseConv3d(IN_CH, OUT_CH, kernel_size)
    up = SparseConvTranspose3d(OUT_CH, IN_CH, kernel_size)
    ref_down = spc.SparseConv3d(IN_CH, OUT_CH, kernel_size, 2, padding=padding, bias=False, indice_key="d")
    ref_up = spc.SparseInverseConv3d(OUT_CH, IN_CH, kernel_size, indice_key="d", bias=False)
    ref_down.weight.data.copy_(spconv_weight(down.weight.data))
    ref_up.weight.data.copy_(spconv_weight(up.weight.data))

    f_ours, f_ref = leaf(feats), leaf(feats)
    x = SparseTensor(f_ours, coords)
    y = down(x)
    r = ref_down(spconv_input(f_ref, coords))

    parents = torch.unique(torch.cat([coords[:, :1], coords[:, 1:].div(2, rounding_mode="floor")], 1), dim=0)
    assert torch.equal(torch.sort(pack(y.coords))[0], pack(parents))
    expected_ref = {(b, *u) for b, *c in coords.tolist() for k in np.ndindex(*(kernel_size,) * 3)
                    if all((ci + padding - ki) % 2 == 0 and 0 <= (ci + padding - ki) // 2 < GRID // 2
                           for ci, ki in zip(c, k))
                    for u in [[(ci + padding - ki) // 2 for ci, ki in zip(c, k)]]}
    assert set(map(tuple, r.indices.tolist())) == expected_ref
    if kernel_size == 2:
        assert len(r.indices) == len(y.coords)
    at = rows_of(y.coords, r.indices.long())
    torch.testing.assert_close(y.features, r.features[at], **FWD)

    g_ours = leaf(torch.randn(len(y.coords), OUT_CH))
    g_ref = torch.zeros(len(r.indices), OUT_CH)
    g_ref[at] = g_ours.detach()
    g_ref.requires_grad_(True)
    z = up(y.replace_features(g_ours), x)
    rz = ref_up(r.replace_feature(g_ref))
    assert z.stride == 1 and torch.equal(z.coords, coords) and torch.equal(rz.indices.long(), coords)
    torch.testing.assert_close(z.features, rz.features, **FWD)

    grad_z = torch.randn_like(z.features)
    z.features.backward(grad_z)
    rz.features.backward(grad_z)
    torch.testing.assert_close(g_ours.grad, g_ref.grad[at], **GRAD)
    torch.testing.assert_close(spconv_weight(up.weight.grad), ref_up.weight.grad, **GRAD)

    grad_y = torch.randn_like(y.features)
    grad_r = torch.zeros_like(r.features)
    grad_r[at] = grad_y
    y.features.backward(grad_y)
    r.features.backward(grad_r)
    torch.testing.assert_close(f_ours.grad, f_ref.grad, **GRAD)
    torch.testing.assert_close(spconv_weight(down.weight.grad), ref_down.weight.grad, **GRAD)


def test_kernel_one_is_a_matmul():
    """(spconv's own 1x1 path reads its weight as view(in, out), not (out, 1, 1, 1, in), so no spconv here.)"""
    coords = random_coords(50, seed=2, grid=6)
    x = SparseTensor(torch.randn(len(coords), 3), coords)
    conv = SubmanifoldConv3d(3, 4, 1, bias=True)
    torch.nn.init.normal_(conv.bias)
    torch.testing.assert_close(conv(x).features, x.features @ conv.weight[0] + conv.bias)
    assert not x.cache


def test_maps_are_built_once_and_shared():
    coords = random_coords(500, seed=3, grid=10)
    x = SparseTensor(torch.randn(len(coords), 2), coords)
    conv_a, conv_b = SubmanifoldConv3d(2, 2), SubmanifoldConv3d(2, 2)
    h = conv_b(conv_a(x))
    assert submanifold_map(h, 3) is submanifold_map(x, 3)
    coarse = SparseConv3d(2, 3, 3)(h)
    assert coarse.cache is x.cache and coarse.stride == 2
    assert torch.equal(SparseConv3d(2, 3, 3)(x).coords, coarse.coords)
    keys_before = set(x.cache)
    out = SparseConvTranspose3d(3, 2, 3)(coarse, h)
    assert set(x.cache) == keys_before and out.cache is x.cache
    assert sparse_cat(out, h).features.shape == (len(x.coords), 4)


def test_dense_table_and_sorted_keys_give_the_same_maps(monkeypatch):
    import perception.sparse as sparse

    coords = random_coords(800, seed=8, grid=12)
    parents = torch.unique(torch.cat([coords[:, :1], coords[:, 1:] // 2], 1), dim=0)
    shifted = [parents + torch.tensor([0, 0, 0, dz]) for dz in (-5, 5)]

    def maps():
        x = SparseTensor(torch.zeros(len(coords), 1), coords)
        built = [submanifold_map(x, k) for k in (1, 3, 5, 7, 9)] + [downsample_map(x, 3)]
        built.append(downsample_map(SparseTensor(x.features, coords), 2))
        return built

    def foreign_parent_maps():
        return [downsample_map(SparseTensor(torch.zeros(len(coords), 1), coords), 3, coarse) for coarse in shifted]

    def no_sorted_keys(x):
        raise AssertionError("a lookup inside the box used the sorted keys")

    with monkeypatch.context() as patch:
        patch.setattr(sparse, "_sorted_keys", no_sorted_keys)
        dense = maps()
    # parents moved off the fine voxels reach outside the padded box: those lookups must not alias
    dense += foreign_parent_maps()
    monkeypatch.setattr(sparse, "DENSE_TABLE_CELLS", 0)
    keyed = maps() + foreign_parent_maps()
    for a, b in zip(dense, keyed, strict=True):
        assert len(a) == len(b)
        for (ia, oa), (ib, ob) in zip(a, b):
            assert (ia is None and ib is None) or (torch.equal(ia, ib) and torch.equal(oa, ob))
    assert sum(len(i) for i, _ in dense[-1]) < sum(len(i) for i, _ in dense[5])  # the unshifted 3^3 map


def test_gradcheck_float64():
    coords = random_coords(40, seed=5, grid=4)
    x = SparseTensor(torch.zeros(len(coords), 1), coords)
    coarse = SparseConv3d(1, 1, 3)(x)
    cases = [(submanifold_map(x, 3), len(coords), len(coords)),
             (downsample_map(x, 3), len(coords), len(coarse.coords)),
             (transpose_map(downsample_map(x, 2)), len(coarse.coords), len(coords))]
    for kmap, n_in, n_out in cases:
        feats = torch.randn(n_in, 2, dtype=torch.float64, requires_grad=True)
        weight = torch.randn(len(kmap), 2, 3, dtype=torch.float64, requires_grad=True)
        bias = torch.randn(3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda f, w: sparse_conv(f, w, kmap, n_out), (feats, weight))
        assert torch.autograd.gradcheck(lambda f, w, b: sparse_conv(f, w, kmap, n_out, b), (feats, weight, bias))


def test_no_wraparound_at_the_edges_of_the_packable_range():
    """Neighbour keys are key + constant: at the range's edges that must not carry into another field."""
    edges = [[0, 0, 0, COORD_MAX], [0, 0, 1, COORD_MIN],  # z + 1 would carry into y
             [0, COORD_MAX, 5, 5], [1, COORD_MIN, 5, 5],  # x + 1 would carry into the batch
             [0, COORD_MAX, COORD_MAX, COORD_MAX], [0, COORD_MIN, COORD_MIN, COORD_MIN]]
    coords = torch.tensor(edges)
    feats = torch.randn(len(coords), 2)
    conv = SubmanifoldConv3d(2, 2, 7)
    x = SparseTensor(feats, coords)
    torch.testing.assert_close(conv(x).features, feats @ conv.weight[7 ** 3 // 2].detach())
    assert sum(len(i) for i, _ in downsample_map(x, 3)) == len(coords)


def test_bad_input_raises_clearly():
    with pytest.raises(ValueError, match="packable range"):
        pack(torch.tensor([[0, COORD_MAX + 1, 0, 0]]))
    with pytest.raises(ValueError, match="packable range"):
        pack(torch.tensor([[-1, 0, 0, 0]]))
    with pytest.raises(ValueError, match="int64"):
        SparseTensor(torch.zeros(1, 2), torch.zeros(1, 4, dtype=torch.int32))
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        SparseTensor(torch.zeros(2, 2), torch.zeros(2, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match="odd"):
        SubmanifoldConv3d(2, 2, 4)
    with pytest.raises(ValueError, match="stride 2"):
        SparseConv3d(2, 2, 3, stride=3)
    coords = random_coords(30, seed=1, grid=5)
    x = SparseTensor(torch.zeros(len(coords), 2), coords)
    with pytest.raises(ValueError, match="stride"):
        SparseConvTranspose3d(2, 2, 3)(x, x)

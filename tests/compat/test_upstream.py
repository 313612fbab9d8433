"""The behaviours the upstream libraries' own test files rely on, checked here against
hand-written references, so they hold in CI without the upstream files:

* every torch_cluster face function scripts with ``torch.jit.script`` and the scripted function
  returns exactly what the eager call returns, errors included;
* torch_cluster master's ``ignore_same_index`` (``radius``, and ``radius_graph`` without loops);
* mmcv's stacked ``ball_query(min_radius, max_radius, sample_num, xyz, center_xyz, xyz_batch_cnt,
  center_xyz_batch_cnt)``;
* mmcv's stacked ``grouping_operation`` giving zeros for indices past their example.

References are NumPy loops in float64 written from the upstream kernels' rules (not from the faces).
The upstream files themselves run with ``tools/upstream/run.sh`` (see ``docs/compat.md``).
"""
import numpy as np
import pytest
import torch

from lidarops.compat import mmcv
from lidarops.compat import torch_cluster as tc

# scripting is what this file tests; torch deprecates torch.jit in favour of torch.compile/export,
# which torch_cluster users do not deploy with yet
pytestmark = pytest.mark.filterwarnings(r"ignore:`torch\.jit\.:DeprecationWarning")

_NAMES = ["fps", "knn", "radius", "knn_graph", "radius_graph"]


@pytest.fixture(scope="module")
def scripted():
    return {name: torch.jit.script(getattr(tc, name)) for name in _NAMES}


def _flat(sizes, F, seed, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(sum(sizes), F, generator=g, dtype=torch.float64).to(dtype)
    batch = torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes))
    return x, batch


# ---------------------------------------------------------------------------------------------
# torch_cluster: scripted == eager
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("F", [1, 2, 3, 6])
def test_scripted_equals_eager(device, scripted, F):
    x, bx = _flat([30, 0, 17, 25], F, seed=F)
    y, by = _flat([7, 4, 0, 9], F, seed=F + 10)
    x, bx, y, by = x.to(device), bx.to(device), y.to(device), by.to(device)
    calls = [
        ("fps", (x, bx, 0.3, False)),
        ("fps", (x, bx, torch.tensor([0.5, 0.2, 0.7, 1.0], device=device), False)),
        ("fps", (x, None, 0.25, False, None, [0, 30, 30, 47, 72])),
        ("fps", (x, None, torch.tensor(0.4, device=device), False, None,
                 torch.tensor([0, 30, 30, 47, 72], device=device))),
        ("knn", (x, y, 3, bx, by)),
        ("knn", (x, y, 5, bx, by, True)),  # cosine
        ("knn", (x[:30], y[:7], 40)),  # k beyond the points
        ("radius", (x, y, 0.45, bx, by, 6)),
        ("radius", (x, x, 0.45, bx, bx, 4, 1, None, True)),  # ignore_same_index
        ("knn_graph", (x, 3, bx)),
        ("knn_graph", (x, 2, bx, True, "target_to_source")),
        ("radius_graph", (x, 0.4, bx)),
        ("radius_graph", (x, 0.4, bx, True, 5, "target_to_source")),
    ]
    for name, args in calls:
        want = getattr(tc, name)(*args)
        got = scripted[name](*args)
        assert got.dtype == want.dtype == torch.int64
        assert torch.equal(got, want), (name, args[2:])


def test_scripted_random_start_matches_eager_with_the_same_seed(scripted):
    x, b = _flat([40, 13], 3, seed=3)
    torch.manual_seed(5)
    want = tc.fps(x, b, 0.5, True)
    torch.manual_seed(5)
    got = scripted["fps"](x, b, 0.5, True)
    assert torch.equal(got, want)


def _error_calls():
    x = torch.rand(10, 3)
    y = torch.rand(4, 3)
    z = torch.zeros(10, dtype=torch.int64)
    nan = x.clone()
    nan[2, 1] = float("nan")
    return [
        ("fps", (x, torch.tensor([0, 0, 1, 1, 0, 1, 1, 1, 1, 1])), "batch must be sorted"),
        ("fps", (x, z, 1.5), "ratio must lie in (0, 1]"),
        ("fps", (x, z, torch.tensor([0.5, 0.5, 0.5])), "ratio must be a float"),
        ("fps", (x, None, 0.5, False, None, [0, 4, 9]), "ptr must rise from 0 to N = 10"),
        ("fps", (x, z, 0.5, False, 0), "batch_size must be a positive int"),
        ("fps", (nan,), "src contains NaN or infinite coordinates"),
        ("fps", (torch.rand(2, 3, 3),), "src must be (N, F)"),
        ("fps", (torch.zeros(10, 3, dtype=torch.int64),), "src must be floating point"),
        ("knn", (x, y, 0), "k must be a positive int"),
        ("knn", (x, torch.rand(4, 2), 2), "x and y must have the same number of features"),
        ("knn", (x, y.double(), 2), "x and y must have the same dtype"),
        ("knn", (x, y, 2, torch.repeat_interleave(torch.tensor([0, 1]), 5)), "batch_x and batch_y must both be given"),
        ("knn", (x, y, 2, z, torch.zeros(3, dtype=torch.int64)), "batch_y must be (N,) with N = 4"),
        ("knn", (x, y, 2, z.float(), None), "batch_x must be an integer tensor"),
        ("radius", (x, y, -1.0), "r must be a finite number >= 0"),
        ("radius", (x, y, float("inf")), "r must be a finite number >= 0"),
        ("radius", (x, y, 0.5, None, None, 0), "max_num_neighbors must be a positive int"),
        ("radius", (x, nan[:4], 0.5), "y contains NaN or infinite coordinates"),
        ("radius", (x, y, 0.5, z - 1, None), "batch_x must be >= 0"),
        ("knn_graph", (x, 2, None, False, "both"), "flow must be 'source_to_target' or 'target_to_source'"),
        ("radius_graph", (x, 0.5, None, False, 32, "up"), "flow must be 'source_to_target' or"),
    ]


@pytest.mark.parametrize("name,args,message", _error_calls(),
                         ids=[f"{c[0]}-{c[2][:24]}" for c in _error_calls()])
def test_scripted_errors_equal_eager(scripted, name, args, message):
    with pytest.raises(ValueError) as eager:
        getattr(tc, name)(*args)
    assert str(eager.value).startswith(message)
    # TorchScript re-raises as torch.jit.Error naming the Python exception type
    with pytest.raises(torch.jit.Error) as script:
        scripted[name](*args)
    assert "ValueError: " + message in str(script.value)


def test_scripted_functions_survive_save_and_load(tmp_path, scripted):
    x, b = _flat([12, 9], 3, seed=7)
    fn = scripted["radius_graph"]
    path = tmp_path / "radius_graph.pt"
    torch.jit.save(fn, str(path))
    loaded = torch.jit.load(str(path))  # a loaded function keeps no defaults: every argument given
    got = loaded(x, 0.5, b, False, 32, "source_to_target", 1, None, False)
    assert torch.equal(got, tc.radius_graph(x, 0.5, b))


# ---------------------------------------------------------------------------------------------
# torch_cluster: ignore_same_index
# ---------------------------------------------------------------------------------------------

def _radius_reference(x, y, r, bx, by, max_nb, ignore_same_index):
    """torch_cluster master's rule: for each y row i, the rows j of x of the same example, in index
    order, with dist2 < r*r, skipping j == i when ignore_same_index (the skip takes no slot)."""
    rows, cols = [], []
    for i in range(len(y)):
        taken = 0
        for j in range(len(x)):
            if bx[j] != by[i] or (ignore_same_index and j == i):
                continue
            if float(((x[j] - y[i]) ** 2).sum()) < r * r and taken < max_nb:
                rows.append(i)
                cols.append(j)
                taken += 1
    return np.array([rows, cols], dtype=np.int64).reshape(2, -1)


@pytest.mark.parametrize("F", [3, 5])
@pytest.mark.parametrize("max_nb", [1, 3, 64])
def test_radius_ignore_same_index_matches_reference(device, F, max_nb):
    x, bx = _flat([25, 0, 18], F, seed=20 + F, dtype=torch.float64)
    y, by = x[:30], bx[:30]  # y rows share flat indices with x, across example boundaries
    want = _radius_reference(x.numpy(), y.numpy(), 0.5, bx.numpy(), by.numpy(), max_nb, True)
    got = tc.radius(x.to(device), y.to(device), 0.5, bx.to(device), by.to(device), max_nb, ignore_same_index=True)
    np.testing.assert_array_equal(got.cpu().numpy(), want)
    # without the flag the query's own row is a hit (distance 0) and takes a slot
    want = _radius_reference(x.numpy(), y.numpy(), 0.5, bx.numpy(), by.numpy(), max_nb, False)
    got = tc.radius(x.to(device), y.to(device), 0.5, bx.to(device), by.to(device), max_nb)
    np.testing.assert_array_equal(got.cpu().numpy(), want)


def test_ignore_same_index_is_by_index_not_by_location(device):
    # duplicates of a query at other indices stay; only the row with the query's own index goes
    x = torch.zeros(4, 3, dtype=torch.float64, device=device)
    got = tc.radius(x, x[:2], 0.1, max_num_neighbors=8, ignore_same_index=True)
    assert got.cpu().tolist() == [[0, 0, 0, 1, 1, 1], [1, 2, 3, 0, 2, 3]]


def test_radius_graph_without_loops_keeps_max_num_neighbors_others(device):
    x, b = _flat([20, 15], 2, seed=31, dtype=torch.float64)
    got = tc.radius_graph(x.to(device), 100.0, b.to(device), max_num_neighbors=3, flow="target_to_source")
    want = _radius_reference(x.numpy(), x.numpy(), 100.0, b.numpy(), b.numpy(), 3, True)
    np.testing.assert_array_equal(got.cpu().numpy(), want)
    assert got.shape[1] == 35 * 3  # every point: 3 other points, none of them itself
    flipped = tc.radius_graph(x.to(device), 100.0, b.to(device), max_num_neighbors=3)
    np.testing.assert_array_equal(flipped.cpu().numpy(), want[::-1])


# ---------------------------------------------------------------------------------------------
# mmcv: stacked ball query
# ---------------------------------------------------------------------------------------------

def _f32_square(r):
    return float(np.float32(r) * np.float32(r))


def _stacked_ball_reference(min_r, max_r, k, xyz, centers, ncnt, mcnt):
    """mmcv's stack kernel rule on float64 points (squares of the float32 radii), with the batch-mode
    inner radius: the first k local indices with d2 == 0 or min_r2 <= d2 < max_r2; the first hit
    fills every slot; no hit gives [-1, 0, 0, ...]."""
    min_r2, max_r2 = _f32_square(min_r), _f32_square(max_r)
    out = np.zeros((len(centers), k), np.int64)
    xs = np.cumsum([0] + list(ncnt))
    row = 0
    for b, m in enumerate(mcnt):
        pts = xyz[xs[b]:xs[b + 1]]
        for _ in range(m):
            d = pts - centers[row]
            d2 = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2]
            hits = [j for j in range(len(pts)) if d2[j] == 0 or min_r2 <= d2[j] < max_r2][:k]
            if hits:
                out[row, :] = hits[0]
                out[row, :len(hits)] = hits
            else:
                out[row, 0] = -1
            row += 1
    return out


@pytest.mark.parametrize("min_r,max_r,k", [(0.0, 0.3, 4), (0.0, 0.6, 64), (0.2, 0.5, 3), (0.25, 0.4, 16)])
def test_stacked_ball_query_matches_reference(device, min_r, max_r, k):
    rng = np.random.default_rng(int(max_r * 100) + k)
    ncnt, mcnt = [40, 0, 25, 30, 12], [6, 3, 0, 8, 5]  # an example without points, one without centres
    xyz = rng.uniform(-1, 1, (sum(ncnt), 3))
    centers = rng.uniform(-1, 1, (sum(mcnt), 3))
    centers[0] = xyz[3]  # d2 == 0 is a hit even inside the inner radius
    want = _stacked_ball_reference(min_r, max_r, k, xyz, centers, ncnt, mcnt)
    got = mmcv.ball_query(min_r, max_r, k, torch.tensor(xyz, device=device), torch.tensor(centers, device=device),
                          torch.tensor(ncnt, dtype=torch.int32, device=device),
                          torch.tensor(mcnt, dtype=torch.int32, device=device))
    assert got.dtype == torch.int32 and got.shape == (sum(mcnt), k)
    np.testing.assert_array_equal(got.cpu().numpy(), want)
    assert (got[6:9].cpu().numpy() == [-1] + [0] * (k - 1)).all()  # the example without points


def test_stacked_ball_query_agrees_with_batch_mode(device):
    # equal-size examples: stacked mode is batch mode flattened, except that no hit gives [-1, 0, ...]
    rng = np.random.default_rng(4)
    xyz = torch.tensor(rng.uniform(-1, 1, (3, 20, 3)), dtype=torch.float32, device=device)
    centers = torch.tensor(rng.uniform(-1, 1, (3, 7, 3)), dtype=torch.float32, device=device)
    batch = mmcv.ball_query(0.1, 0.45, 5, xyz, centers)
    cnt = torch.tensor([20, 20, 20], dtype=torch.int32, device=device)
    stacked = mmcv.ball_query(0.1, 0.45, 5, xyz.reshape(-1, 3), centers.reshape(-1, 3), cnt, cnt.new_tensor([7] * 3))
    want = batch.reshape(-1, 5).clone()
    d2 = ((centers[:, :, None] - xyz[:, None]) ** 2).sum(-1).reshape(-1, 20)
    none = ~((d2 < 0.45 ** 2) & ((d2 == 0) | (d2 >= 0.1 ** 2))).any(1)
    want[none, 0] = -1
    assert torch.equal(stacked, want)


def test_stacked_ball_query_bad_input():
    xyz, c = torch.rand(10, 3), torch.rand(4, 3)
    cnt_x, cnt_c = torch.tensor([6, 4], dtype=torch.int32), torch.tensor([2, 2], dtype=torch.int32)
    with pytest.raises(ValueError, match="both xyz_batch_cnt and center_xyz_batch_cnt"):
        mmcv.ball_query(0, 0.2, 4, xyz, c, cnt_x)
    with pytest.raises(ValueError, match="sum to 10"):
        mmcv.ball_query(0, 0.2, 4, xyz, c, torch.tensor([6, 3], dtype=torch.int32), cnt_c)
    with pytest.raises(ValueError, match="same length"):
        mmcv.ball_query(0, 0.2, 4, xyz, c, cnt_x, torch.tensor([4], dtype=torch.int32))
    with pytest.raises(ValueError, match="N1 \\+ N2"):
        mmcv.ball_query(0, 0.2, 4, xyz[None], c, cnt_x, cnt_c)
    with pytest.raises(ValueError, match="min_radius must be < max_radius"):
        mmcv.ball_query(0.3, 0.2, 4, xyz, c, cnt_x, cnt_c)
    with pytest.raises(ValueError, match="integer"):
        mmcv.ball_query(0, 0.2, 4, xyz, c, cnt_x.float(), cnt_c)


# ---------------------------------------------------------------------------------------------
# mmcv: stacked grouping past the example
# ---------------------------------------------------------------------------------------------

def test_stacked_grouping_zeros_past_the_example(device):
    rng = np.random.default_rng(12)
    n_cnt, m_cnt = [4, 6, 0, 5], [3, 2, 2, 3]
    feats = rng.normal(size=(sum(n_cnt), 5))
    idx = rng.integers(-1, 9, (sum(m_cnt), 6)).astype(np.int32)  # many indices >= N_b
    starts = np.cumsum([0] + n_cnt[:-1])
    example = np.repeat(np.arange(4), m_cnt)
    want = np.zeros((sum(m_cnt), 5, 6))
    for i in range(len(idx)):
        for s in range(6):
            j = idx[i, s]
            if 0 <= j < n_cnt[example[i]]:
                want[i, :, s] = feats[starts[example[i]] + j]
    f = torch.tensor(feats, device=device, requires_grad=True)
    args = (torch.tensor(idx, device=device), torch.tensor(n_cnt, dtype=torch.int32, device=device),
            torch.tensor(m_cnt, dtype=torch.int32, device=device))
    got = mmcv.grouping_operation(f, *args)
    np.testing.assert_array_equal(got.detach().cpu().numpy(), want)
    # the gradient reaches only the rows that were read
    got.sum().backward()
    reads = np.zeros(len(feats))
    for i in range(len(idx)):
        for j in idx[i]:
            if 0 <= j < n_cnt[example[i]]:
                reads[starts[example[i]] + j] += 1
    np.testing.assert_array_equal(f.grad.cpu().numpy(), np.repeat(reads[:, None], 5, 1))


def test_stacked_grouping_below_minus_one_raises():
    with pytest.raises(ValueError, match="indices must be >= -1 in stacked mode"):
        mmcv.grouping_operation(torch.rand(5, 3), torch.full((2, 4), -2, dtype=torch.int32),
                                torch.tensor([5], dtype=torch.int32), torch.tensor([2], dtype=torch.int32))

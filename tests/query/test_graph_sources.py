"""The index's counter source through CounterNet's CUDA graph (lidarops.query.build.CounterSource, graph=True)
against the eager source, batch by batch as build_index calls it; without the index itself, so that it runs
where DuckDB is not installed (the GPU machine)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lidarops.models.counternet import CounterNet
from lidarops.query.build import CounterSource, Scan
from lidarops.query.index import QueryError

from tests.models.test_counternet import _tiny_cfg


def test_counter_source_graph_needs_a_dense_counternet_on_cuda():
    cpu = CounterNet(_tiny_cfg()).eval()
    assert CounterSource(cpu).graph is False  # on the CPU: eager
    with pytest.raises(QueryError, match="graph=True needs a CounterNet with backbone_mode='dense' on a CUDA device"):
        CounterSource(cpu, graph=True)
    with pytest.raises(QueryError, match="graph must be True, False or None"):
        CounterSource(cpu, graph=1)
    with pytest.raises(QueryError, match="optimize must be True or False"):
        CounterSource(cpu, optimize=1)
    if torch.cuda.is_available():
        assert CounterSource(cpu.cuda()).graph is True


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
@pytest.mark.parametrize("partitions, delta", [(1, 0.0), (4, 0.2)])
def test_graph_counter_source_equals_the_eager_one(partitions, delta):
    """Batches of 4 (ragged frames, an empty one, a larger frame recording the graph again, a batch needing more
    pillar rows, frames needing more peak rows, a short last batch): the same counts and centres as the eager
    source; a bad intensity raises the eager check's message."""
    from tests.models.test_counternet_graph import _model

    model = _model(partitions, delta).cuda()
    g = torch.Generator().manual_seed(5)
    scans = [Scan(torch.rand(n, 4, generator=g) * torch.tensor([15.0, 15.0, 3.0, 1.0]) + torch.tensor([0, -7.5, -2.5, 0]))
             for n in (300, 0, 40, 7, 12, 5, 900, 30, 300, 40000, 300, 300, 20)]
    eager = CounterSource(model, graph=False)
    graph = CounterSource(model, graph=True)
    graph.pillar_step = 1  # pillar rows sized to the first batch: a later one needs more
    graph.max_peaks = 64  # frames with more peaks are counted eagerly, then the graph gets more rows
    found = 0
    for start in range(0, len(scans), 4):
        batch = scans[start:start + 4]
        want, got = eager(batch), graph(batch)
        assert [c for c, _ in got] == [c for c, _ in want], f"batch at {start}"
        for (_, centres), (_, ref) in zip(got, want):
            assert [c[0] for c in centres] == [c[0] for c in ref]
            np.testing.assert_allclose([c[1:] for c in centres], [c[1:] for c in ref], rtol=0, atol=1e-5)
            found += len(ref)
    assert found > 0, "the case must count objects"
    assert graph.eager_batches >= 1 and graph.max_peaks > 64 and graph._graphed.capacity >= 40000
    bad = Scan(scans[0].points.clone())
    bad.points[3, 3] = float("nan")
    with pytest.raises(ValueError, match=r"frame\(s\) \[1\] of this batch: batch\['points'\]\[:, 4:\] \(intensity"):
        graph([scans[2], bad])

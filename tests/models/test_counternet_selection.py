"""SelectedCounter (lidarops/models/counternet_selection.py): frames assigned to the model whose counts are
nearest their labels, the selector fitted on the feature model's features, and each frame counted by the model
the selector picks for it."""
from __future__ import annotations

import pytest
import torch

from lidarops.models.counternet import CounterNet
from lidarops.models.counternet_selection import SelectedCounter

from .test_counternet import SCENES, _batch, _scene, _tiny_cfg


def _models():
    torch.manual_seed(0)
    a = CounterNet(_tiny_cfg(1, 0.0, THRESHOLD=0.05, OTSU=False)).eval()
    torch.manual_seed(1)
    b = CounterNet(_tiny_cfg(4, 0.2, THRESHOLD=0.05, OTSU=False)).eval()
    return [a, b]


BATCHES = [_batch([_scene(i, SCENES[i % 2]), _scene(10 + i, SCENES[(i + 1) % 2])]) for i in range(3)]


def test_fit_assigns_each_frame_to_its_nearest_model():
    models = _models()
    counter = SelectedCounter(models).fit(BATCHES, epsilon=0.5)
    want_err = []
    for batch in BATCHES:
        per = [[int((f["counts"] - f["true_counts"]).abs().sum()) for f in m.predict(batch)] for m in models]
        want_err += list(zip(*per))
    assert counter.errors.tolist() == [list(e) for e in want_err]
    assert counter.best.tolist() == [min(range(2), key=lambda m: (e[m], m)) for e in want_err]
    feats = torch.cat([models[0](b)["features"] for b in BATCHES]).double()
    for m in range(2):
        frames = counter.best == m
        if frames.any():
            torch.testing.assert_close(counter.selector.centres[m], feats[frames].mean(0))
    assert int(counter.selector.counts.sum()) == 6


def test_predict_counts_each_frame_with_its_chosen_model():
    models = _models()
    counter = SelectedCounter(models).fit(BATCHES, epsilon=0.5)
    batch = BATCHES[1]
    choice = counter.choose(batch)
    want = counter.selector.select(models[0](batch)["features"].double())
    assert choice.tolist() == want.tolist()
    got = counter.predict(batch)
    for b, frame in enumerate(got):
        own = models[frame["model"]].predict(batch)[b]
        assert frame["model"] == int(choice[b]) and torch.equal(frame["counts"], own["counts"])


def test_one_model_needs_no_selector_and_errors_are_named():
    models = _models()
    single = SelectedCounter(models[:1])
    assert [f["model"] for f in single.predict(BATCHES[0])] == [0, 0]
    with pytest.raises(ValueError, match="fit"):
        SelectedCounter(models).predict(BATCHES[0])
    with pytest.raises(ValueError, match="at least one"):
        SelectedCounter([])
    with pytest.raises(ValueError, match="feature_model"):
        SelectedCounter(models, feature_model=2)
    other = CounterNet(_tiny_cfg()).eval()
    other.config.floor["class_names"] = ["Car", "Truck"]
    with pytest.raises(ValueError, match="same classes"):
        SelectedCounter([models[0], other])
    with pytest.raises(ValueError, match="gt_boxes"):
        SelectedCounter(models).fit([{k: v for k, v in BATCHES[0].items() if k != "gt_boxes"}], 0.5)
    with pytest.raises(ValueError, match="empty"):
        SelectedCounter(models).fit([], 0.5)


def test_selected_counter_is_a_count_source():
    pytest.importorskip("duckdb")
    from lidarops.query.build import CounterSource

    class _Frame:
        def __init__(self, points):
            self.points = points

    counter = SelectedCounter(_models()).fit(BATCHES, epsilon=0.5)
    batch = BATCHES[0]
    frames = [_Frame(batch["points"][batch["points"][:, 0] == b, 1:]) for b in range(2)]
    out = CounterSource(counter)(frames)
    want = counter.predict({"points": batch["points"], "batch_size": 2})
    assert [list(c.values()) for c, _, _ in out] == [w["counts"].tolist() for w in want]
    assert [name for _, _, name in out] == [f"model{w['model']}" for w in want]  # the model of each frame


def _save_members(tmp_path, models):
    from lidarops.checkpoint import format_fields, save_checkpoint

    paths = []
    for i, m in enumerate(models):
        paths.append(tmp_path / f"member{i}.pth")
        save_checkpoint({**format_fields(), "model_class": "CounterNet", "model_config": m.config.to_dict(),
                         "class_names": m.config.class_names, "model_state": m.state_dict()}, [paths[-1]])
    return paths


def test_selection_saved_and_loaded_counts_the_same_and_indexes_each_frames_model(tmp_path):
    """save / load (lidarops.models.load_model) give the same choices and counts; the members are named by their
    files; build_index with the loaded selection writes each frame's model in the index's ``model`` column."""
    pytest.importorskip("duckdb")
    from lidarops.checkpoint import CheckpointError
    from lidarops.models import load_model
    from lidarops.query import FrameIndex
    from lidarops.query.build import CounterSource, Scan, build_index

    models = _models()
    counter = SelectedCounter(models).fit(BATCHES, epsilon=0.5)
    paths = _save_members(tmp_path, models)
    counter.save(tmp_path / "sel" / "selection.pth", paths)
    loaded = load_model(tmp_path / "sel" / "selection.pth")
    assert type(loaded).__name__ == "SelectedCounter" and loaded.names == ["member0", "member1"]
    for batch in BATCHES:
        assert loaded.choose(batch).tolist() == counter.choose(batch).tolist()
        got, want = loaded.predict(batch), counter.predict(batch)
        assert [g["counts"].tolist() for g in got] == [w["counts"].tolist() for w in want]
    # moved with its members: relative paths still resolve
    (tmp_path / "moved").mkdir()
    for f in (tmp_path / "sel" / "selection.pth", *paths):
        f.rename(tmp_path / "moved" / f.name)
    counter.save(tmp_path / "moved" / "selection.pth", [tmp_path / "moved" / p.name for p in paths])
    moved = SelectedCounter.load(tmp_path / "moved" / "selection.pth")
    frames = {}
    for batch in BATCHES:
        for b in range(int(batch["batch_size"])):
            frames[len(frames)] = Scan(batch["points"][batch["points"][:, 0] == b, 1:].contiguous())
    build_index(tmp_path / "idx", list(frames), frames.__getitem__, CounterSource(moved), batch=2)
    rows = FrameIndex.open(tmp_path / "idx").sql("SELECT frame_id, model FROM counts ORDER BY frame_id")
    chosen = []
    for start in range(0, len(frames), 2):
        pts = torch.cat([torch.cat([torch.full((len(frames[i].points), 1), float(i - start)), frames[i].points], 1)
                         for i in range(start, min(start + 2, len(frames)))])
        chosen += moved.choose({"points": pts, "batch_size": min(2, len(frames) - start)}).tolist()
    assert rows["model"].tolist() == [f"member{m}" for m in chosen]
    (tmp_path / "moved" / "member1.pth").unlink()
    with pytest.raises(CheckpointError, match="member 'member1.pth' is neither a file"):
        load_model(tmp_path / "moved" / "selection.pth")


class _FakeCounter(torch.nn.Module):
    """A counter whose counts per frame are given: model ``k`` reads ``batch["counts"][k]``; the features are
    ``batch["features"]`` (what the feature model would compute)."""

    def __init__(self, k):
        super().__init__()
        self.k = k
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.config = type("C", (), {"class_names": ["Car", "Pedestrian"]})()

    def forward(self, batch):
        return {"features": batch["features"]}

    def predict(self, batch):
        return [{"counts": c, "true_counts": t} for c, t in zip(batch["counts"][self.k], batch["true"])]


def test_frames_go_to_the_model_that_counts_their_kind_best():
    # crowded frames (features near (5, 5)): model 1 counts them right; sparse ones (near (0, 0)): model 0
    g = torch.Generator().manual_seed(0)
    crowded = torch.tensor([True, False, True, False, False, True])  # both kinds, whatever the global RNG holds
    feats = torch.where(crowded[:, None], torch.tensor([5.0, 5.0]), torch.tensor([0.0, 0.0])) + \
        0.3 * torch.randn(6, 2, generator=g)
    true = torch.randint(0, 20, (6, 2), generator=g)
    off = torch.tensor([3, 2])
    counts = [torch.where(crowded[:, None], true + off, true), torch.where(crowded[:, None], true, true + off)]
    batch = {"features": feats, "true": true, "counts": counts, "batch_size": 6, "gt_boxes": torch.zeros(6, 1, 8)}
    counter = SelectedCounter([_FakeCounter(0), _FakeCounter(1)]).fit([batch], epsilon=0.5)
    assert counter.best.tolist() == crowded.long().tolist()
    test = {"features": torch.tensor([[5.2, 4.9], [0.1, -0.2]]), "true": true[:2], "counts": [c[:2] for c in counts],
            "batch_size": 2}
    assert counter.choose(test).tolist() == [1, 0]
    got = counter.predict(test)
    assert [f["model"] for f in got] == [1, 0]
    assert torch.equal(got[0]["counts"], counts[1][0]) and torch.equal(got[1]["counts"], counts[0][1])

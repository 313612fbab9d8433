"""lidarops.models.sscater_calibration: the calibration of SSCATeR's model that ``lidarops stream``, the benchmarks
and the profiles share (layer labels, the share of zero ReLU outputs reached on a window)."""
import pytest
import torch

from lidarops.models import sscater_calibration as calibration


def test_layer_labels():
    pfn, backbone = calibration.build_model(True, 0, torch.float32, "cpu")
    labels = calibration.layer_labels(backbone)
    assert len(labels) == 19
    assert labels["block0.down0"] == "block 1 conv 1 (3x3, stride 2)"
    assert labels["block0.subm3"] == "block 1 conv 4 (3x3)"
    assert labels["block1.down4"] == "block 2 conv 1 (3x3, stride 2)"
    assert labels["block2.subm15"] == "block 3 conv 6 (3x3)"
    assert [labels[f"up{b}"] for b in range(3)] == ["upsampling of block 1 (x1)", "upsampling of block 2 (x2)",
                                                    "upsampling of block 3 (x4)"]


@pytest.mark.parametrize("share", [0.5, 0.8])
def test_calibrate_on_window_reaches_the_relu_zero_share(share):
    """The calibration the CLI, the benchmark and the profiles share: on the window it was calibrated on,
    each layer's share of zero ReLU outputs is the target (up to ties and rounding); the model is reset."""
    from lidarops.data.synthetic import Simulator
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    from lidarops.ops.pillars import PillarGrid
    pfn, backbone = calibration.build_model(True, 0, torch.float32, "cpu")
    model = SSCATeRPointPillars(pfn, backbone, PillarGrid.drone(), max_points_per_pillar=100, device="cpu")
    for i, (p, t) in enumerate(Simulator("drone_bridge", seed=0).slices(0.0, 0.1, 0.01)):
        model.step(torch.from_numpy(p), torch.from_numpy(t), now=0.01 * (i + 1))
    shares = calibration.calibrate_on_window(model, share)
    assert set(calibration.layer_labels(backbone)) | {"pfn"} == set(shares)
    assert all(abs(v - share) < 0.05 for v in shares.values()), shares
    assert model.stream.num_points == 0 and model.stats.step == 0

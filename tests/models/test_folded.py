"""lidarops.models.folded: a 1x1 convolution with the BatchNorm after it folded into one affine map (eval mode),
against the two modules; what it refuses."""
from __future__ import annotations

import pytest
import torch
from torch import nn
from torch.nn import functional as F

from lidarops.models import folded
from helpers.models import randomize_bn


@pytest.mark.parametrize("bias", [False, True])
def test_conv_bn_equals_the_modules_in_eval_mode(bias):
    torch.manual_seed(0)
    conv, bn = nn.Conv1d(5, 7, 1, bias=bias).double(), nn.BatchNorm1d(7).double()
    randomize_bn(bn, 3)
    bn.eval()
    x = torch.randn(2, 5, 9, dtype=torch.float64)
    w, b = folded.conv_bn(conv, bn)
    assert w.shape == (7, 5) and b.shape == (7,)
    torch.testing.assert_close(F.linear(x.transpose(1, 2), w, b).transpose(1, 2), bn(conv(x)), rtol=1e-12, atol=1e-12)
    w, b = folded.conv_bn(conv)  # no BatchNorm: the convolution itself (a zero bias without one)
    torch.testing.assert_close(F.linear(x.transpose(1, 2), w, b).transpose(1, 2), conv(x), rtol=1e-12, atol=1e-12)


def test_conv_bn_refuses_what_it_cannot_fold():
    with pytest.raises(ValueError, match="1x1 convolutions"):
        folded.conv_bn(nn.Conv1d(4, 4, 3))
    with pytest.raises(ValueError, match="1x1 convolutions"):
        folded.conv_bn(nn.Conv1d(4, 4, 1, groups=2))
    with pytest.raises(ValueError, match="no running statistics"):
        folded.conv_bn(nn.Conv1d(4, 4, 1), nn.BatchNorm1d(4, track_running_stats=False))


def test_cached_rebuilds_after_a_change_and_per_dtype():
    conv = nn.Conv1d(3, 2, 1)
    calls = []

    def build():
        calls.append(1)
        return folded.conv_bn(conv)

    a = folded.cached(conv, "w", torch.float32, build)
    assert folded.cached(conv, "w", torch.float32, build) is a and len(calls) == 1
    assert folded.cached(conv, "w", torch.float64, build)[0].dtype == torch.float64 and len(calls) == 2
    with torch.no_grad():
        conv.weight.add_(1.0)
    b = folded.cached(conv, "w", torch.float32, build)
    assert len(calls) == 3 and b is not a and torch.equal(b[0], conv.weight[:, :, 0])
    assert folded.compute_dtype(torch.zeros(1, dtype=torch.float64)) == torch.float64

"""The I3D extractor (FVD proper): a network built here, saved as safetensors with the port's parameter names,
loaded back strictly through ``extractor_for``; features, labels and refusals."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from marionette.eval.fvd import FVD_LABEL, extractor_for, fvd_report
from marionette.eval.i3d import I3DExtractor, InceptionI3d, same_pad


def test_same_padding_matches_tensorflow():
    x = torch.zeros(1, 1, 9, 224, 223)
    # kernel 7, stride 2: an odd size pads k − (size mod s) = 6, an even one k − s = 5 (2 in front, 3 behind)
    assert same_pad(x, (7, 7, 7), (2, 2, 2)).shape[2:] == (15, 229, 229)
    assert same_pad(torch.zeros(1, 1, 4, 8, 8), (3, 3, 3), (2, 2, 2)).shape[2:] == (5, 9, 9)  # pad 1: 0 front, 1 back
    y = same_pad(torch.ones(1, 1, 4, 8, 8), (3, 3, 3), (2, 2, 2))
    assert float(y[0, 0, 0].sum()) == 64 and float(y[0, 0, -1].sum()) == 0  # the extra row goes behind


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    torch.manual_seed(0)
    net = InceptionI3d().eval()
    with torch.no_grad():  # non-trivial batch-norm statistics, so a wrong mapping would show
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm3d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    path = tmp_path_factory.mktemp("i3d") / "i3d_kinetics400.safetensors"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(path))
    return path, net


def test_loads_strictly_and_extracts_the_time_averaged_logits(weights):
    path, net = weights
    ex = extractor_for(path)
    assert isinstance(ex, I3DExtractor) and ex.is_fvd
    assert all(torch.equal(a, b) for a, b in zip(ex.network.state_dict().values(), net.state_dict().values()))
    g = torch.Generator().manual_seed(1)
    videos = torch.rand(2, 9, 3, 36, 64, generator=g) * 2 - 1
    f = ex.extract(videos)
    assert f.shape == (2, 400) and f.dtype == np.float64 and np.isfinite(f).all()
    x = torch.nn.functional.interpolate(videos.flatten(0, 1), size=(224, 224), mode="bilinear").view(2, 9, 3, 224, 224)
    with torch.no_grad():
        direct = net(x.transpose(1, 2)).mean(-1).double().numpy()
    np.testing.assert_allclose(f, direct, rtol=1e-5, atol=1e-6)
    assert not np.allclose(f[0], f[1])
    assert fvd_report(videos, videos.flip(1), ex, resamples=4)["metric"] == FVD_LABEL
    with pytest.raises(ValueError, match="at least 9"):
        ex.extract(videos[:, :8])


def test_a_file_of_other_names_or_shapes_is_refused_by_name(weights, tmp_path):
    path, net = weights
    state = {k: v.contiguous() for k, v in net.state_dict().items()}
    renamed = dict(state)
    renamed["Mixed_4b.branch0.conv3d.weight"] = renamed.pop("Mixed_4b.b0.conv3d.weight")
    save_file(renamed, str(tmp_path / "renamed.safetensors"))
    with pytest.raises(ValueError, match=r"missing \[Mixed_4b\.b0\.conv3d\.weight\].*unexpected \[Mixed_4b\.branch0"):
        extractor_for(tmp_path / "renamed.safetensors")
    reshaped = dict(state)
    reshaped["Conv3d_2b_1x1.conv3d.weight"] = torch.zeros(64, 64, 3, 1, 1)
    save_file(reshaped, str(tmp_path / "reshaped.safetensors"))
    with pytest.raises(ValueError, match=r"other shapes \[Conv3d_2b_1x1\.conv3d\.weight\]"):
        extractor_for(tmp_path / "reshaped.safetensors")


def test_observation_rows_use_i3d_when_given(weights):
    """The report's observation rows with the I3D extractor: labelled FVD, per-chunk pieces of ≥ 9 frames."""
    from marionette.eval.clips import _chunk_frames, observation_fvd
    from marionette.observation.config import ObservationConfig
    from marionette.observation.model import VideoDiT

    ex = extractor_for(weights[0])
    model = VideoDiT(ObservationConfig(frames=5, height=18, width_px=32, patch=2, width=32, layers=1, heads=2), seed=0)
    g = torch.Generator().manual_seed(2)
    clips = [(torch.rand(9, 3, 18, 32, generator=g) * 2 - 1, torch.rand(9, 3, 18, 32, generator=g)) for _ in range(2)]
    r = observation_fvd(model, clips, steps=2, resamples=4, extractor=ex)
    assert r["frames"] == 9 and r["whole"]["metric"] == FVD_LABEL and np.isfinite(r["whole"]["value"])
    assert [c["metric"] for c in r["per_chunk"]] == [FVD_LABEL]  # one 9-frame piece: two model chunks
    assert _chunk_frames(5, ex, 41) == 9 and _chunk_frames(17, ex, 41) == 17 and _chunk_frames(5, ex, 7) == 7

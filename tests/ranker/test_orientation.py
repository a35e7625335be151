"""The learned ranking's edge-orientation columns (reeb_torch.ranker.orientation): the bins
by hand, the box sums against brute force, the generator computing them only for a model
that reads them, and the fit's choice of columns."""

from __future__ import annotations

import math

import pytest
import torch

from reeb_torch import ProposalGenerator, ReebConfig
from reeb_torch.ranker import fit as RF
from reeb_torch.ranker import ORIENTATION_NAMES, BoxRanker, save_ranker
from reeb_torch.ranker import orientation as O
from reeb_torch.ranker.features import feature_names


def _shares(grey: torch.Tensor, box: list[int]) -> torch.Tensor:
    ii = O.orientation_integrals(grey[None])
    return O.orientation_features(ii, torch.tensor([box]), torch.zeros(1, dtype=torch.long))[0]


@pytest.mark.parametrize("image, bin_", [
    (lambda y, x: (x >= 20).double(), 0),          # a vertical edge: the gradient across, bin 0
    (lambda y, x: (y >= 20).double(), 2),          # a horizontal edge: bin 2
    (lambda y, x: (x + y >= 40).double(), 1),      # rising to the lower right: gx · gy > 0
    (lambda y, x: (x - y >= 0).double(), 3),       # gx · gy < 0
])
def test_each_edge_direction_falls_in_its_bin(image, bin_):
    y, x = torch.meshgrid(torch.arange(40), torch.arange(40), indexing="ij")
    grey = image(y, x).float()
    s = _shares(grey, [5, 5, 35, 35])
    assert s.shape == (8,) and s.dtype == torch.float32
    assert float(s[bin_]) > 0.99 and float(s[:4].sum()) == pytest.approx(1.0, abs=1e-5)
    assert float(s[4 + bin_]) > 0.99  # the edge crosses the border band too


def test_the_band_is_the_box_less_its_shrunk_inside():
    grey = torch.zeros(60, 60)
    grey[:, 12:] = 1.0  # a vertical edge at column 12: in the band of box (10, 10)-(50, 50)
    s = _shares(grey, [10, 10, 50, 50])
    assert float(s[0]) > 0.99 and float(s[4]) > 0.99
    grey = torch.zeros(60, 60)
    grey[20:40, 20:40] = 1.0  # a square well inside the band (6 px of the 40): its sides inside only
    s = _shares(grey, [10, 10, 50, 50])
    assert float(s[4:].sum()) < 1e-3
    assert float(s[0]) == pytest.approx(float(s[2]), abs=0.02) and float(s[0] + s[2]) > 0.8


def test_box_sums_are_brute_force_sums():
    g = torch.Generator().manual_seed(0)
    grey = torch.rand(2, 30, 50, generator=g)
    ii = O.orientation_integrals(grey)
    assert ii.shape == (2, 31, 51, 4) and ii.dtype == torch.float64
    # the bins by atan2, pixel by pixel
    p = torch.nn.functional.pad(grey.double()[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = (p[:, :-2, 2:] + 2 * p[:, 1:-1, 2:] + p[:, 2:, 2:] - p[:, :-2, :-2] - 2 * p[:, 1:-1, :-2] - p[:, 2:, :-2]) / 8
    gy = (p[:, 2:, :-2] + 2 * p[:, 2:, 1:-1] + p[:, 2:, 2:] - p[:, :-2, :-2] - 2 * p[:, :-2, 1:-1] - p[:, :-2, 2:]) / 8
    theta = torch.atan2(gy, gx) % math.pi
    bins = torch.round(theta / (math.pi / 4)).long() % 4
    mag = torch.sqrt(gx * gx + gy * gy)
    boxes = torch.tensor([[0, 0, 50, 30], [3, 4, 17, 29], [20, 1, 21, 2], [10, 10, 40, 20]])
    bi = torch.tensor([0, 1, 1, 0])
    out = O.orientation_features(ii, boxes, bi)
    for k, ((x0, y0, x1, y1), b) in enumerate(zip(boxes.tolist(), bi.tolist())):
        sums = torch.stack([(mag[b, y0:y1, x0:x1] * (bins[b, y0:y1, x0:x1] == j)).sum() for j in range(4)])
        torch.testing.assert_close(out[k, :4], (sums / (sums.sum() + 1e-6)).float(), atol=1e-5, rtol=0)


def test_the_compiled_passes_are_the_tensor_path():
    """The CPU kernels give the tensor ops' numbers (the CUDA path's): every pixel in the same
    bin, the tables to float64 rounding (torch's running sums may add in another order), the
    shares to float32 rounding."""
    g = torch.Generator().manual_seed(2)
    grey = torch.rand(3, 37, 53, generator=g)
    grey[1] = (grey[1] > 0.5).float()  # flat areas, steps and ties
    ii, ref = O.orientation_integrals(grey), O._integrals_tensor(grey)
    torch.testing.assert_close(ii, ref, atol=1e-9, rtol=0)

    def pixels(t):
        return t[:, 1:, 1:] - t[:, :-1, 1:] - t[:, 1:, :-1] + t[:, :-1, :-1]

    assert torch.equal(pixels(ii) > 1e-9, pixels(ref) > 1e-9)
    x0 = torch.randint(0, 45, (500,), generator=g)
    y0 = torch.randint(0, 30, (500,), generator=g)
    boxes = torch.stack([x0, y0, (x0 + torch.randint(1, 9, (500,), generator=g)).clamp(max=53),
                         (y0 + torch.randint(1, 8, (500,), generator=g)).clamp(max=37)], 1)
    bi = torch.randint(0, 3, (500,), generator=g)
    torch.testing.assert_close(O.orientation_features(ii, boxes, bi), O._features_tensor(ii, boxes, bi),
                               atol=1e-6, rtol=0)


def _orientation_model(names) -> BoxRanker:
    torch.manual_seed(0)
    return BoxRanker(names, hidden=(8,), classes=("Car", "Pedestrian", "Cyclist", "Truck")).eval()


def test_the_generator_computes_the_columns_a_model_reads(sample_image, tmp_path, monkeypatch):
    with_path = save_ranker(_orientation_model(feature_names(4) + ORIENTATION_NAMES), tmp_path / "with.safetensors")
    without_path = save_ranker(_orientation_model(feature_names(4)), tmp_path / "without.safetensors")
    gen = ProposalGenerator(ReebConfig(ranker=str(with_path), top_k=100))
    c = gen.candidates(sample_image)
    assert c.feature_names == feature_names(4) + ORIENTATION_NAMES and c.features.shape[1] == 55
    shares = c.features[:, -8:]
    torch.testing.assert_close(shares[:, :4].sum(1), torch.ones(len(shares)), atol=1e-3, rtol=0)
    assert float(shares.min()) >= 0 and float(shares.max()) <= 1
    assert len(gen([sample_image])[0]["boxes"]) == 100
    # the candidates reeb fit fits on hold them too, whatever the model
    assert ProposalGenerator(ReebConfig(ranker="none")).candidates(sample_image).features.shape[1] == 55
    # a model without them: never computed
    monkeypatch.setattr(O, "orientation_integrals", lambda grey: pytest.fail("computed for a model without them"))
    old = ProposalGenerator(ReebConfig(ranker=str(without_path), top_k=100))
    assert old.candidates(sample_image).features.shape[1] == 47
    assert len(old([sample_image])[0]["boxes"]) == 100


def test_the_fit_reads_the_orientation_columns_unless_told_not_to(tmp_path):
    names = feature_names(4) + ORIENTATION_NAMES
    g = torch.Generator().manual_seed(1)
    x = torch.rand(3000, len(names), generator=g)
    y = (x[:, -8] > 0.7).float()  # the label is an orientation column's
    samples = [RF.Sample(x, y, torch.ones(len(x)), torch.where(y > 0, 0, -1))]
    opts = RF.FitOptions(epochs=3, hidden=(8,), batch=512, class_hidden=None)
    both = RF.fit_ranker(samples, names, opts)
    base = RF.fit_ranker(samples, names, RF.FitOptions(epochs=3, hidden=(8,), batch=512, class_hidden=None,
                                                     orientation=False))
    assert both.feature_names == names and base.feature_names == feature_names(4)
    # fine-tuning a model without them on samples with them reads the model's own columns
    path = save_ranker(base, tmp_path / "base.safetensors")
    tuned = RF.fit_ranker(samples, names, RF.FitOptions(init=str(path), class_hidden=None))
    assert tuned.feature_names == feature_names(4)
    with pytest.raises(ValueError, match="hold 55 feature columns"):
        RF.fit_ranker(samples, feature_names(4), opts)

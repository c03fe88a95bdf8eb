"""Companions injected into cubes (kpifs.inject, kpifs inject)."""
import hashlib

import numpy as np
import pytest
import astropy.units as u
from astropy.io import fits

from kpifs import KpifsError, KpifsWarning
from kpifs.cli import main
from kpifs.inject import inject_companion, shift_images, sky_to_detector


def _gauss(x0, y0, n=48, s=2.5):
    y, x = np.mgrid[:n, :n]
    return np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * s ** 2))


def test_subpixel_shift_is_exact_for_band_limited_images():
    out = shift_images(_gauss(20.0, 24.0), 2.3, -1.7)
    np.testing.assert_allclose(out, _gauss(22.3, 22.3), atol=2e-6)
    # nothing wraps round: a shift off the edge leaves zeros, not the other side
    assert np.abs(shift_images(_gauss(44.0, 24.0), 10.0, 0.0)[:, :20]).max() < 1e-6


def test_inject_detector_and_sky():
    cube = np.stack([_gauss(24.0, 24.0)] * 2)[None].repeat(2, axis=0)     # (2, 2, 48, 48)
    det = inject_companion(cube, position=[30, -20] * u.mas, contrast=[0.1, 0.2],
                           pixscale=10 * u.mas)
    want = np.array([0.1, 0.2])[None, :, None, None] * _gauss(27.0, 22.0)[None, None]
    np.testing.assert_allclose(det - cube, np.broadcast_to(want, cube.shape), atol=1e-6)
    # on the sky, frames at different detector angles see the companion at their own
    # detector offsets: x = -dRA cos t + dDec sin t, y = dRA sin t + dDec cos t
    sky = inject_companion(cube, position=[30, -20] * u.mas, contrast=0.1, frame="sky",
                           pixscale=10 * u.mas, detpa=[0.0, 90.0])
    for f, t in enumerate((0.0, 90.0)):
        x, y = sky_to_detector(30.0, -20.0, t)
        np.testing.assert_allclose(sky[f, 0] - cube[f, 0],
                                   0.1 * _gauss(24 + x / 10, 24 + y / 10), atol=1e-6)
    with pytest.raises(KpifsError, match="detector position angle"):
        inject_companion(cube, position=[30, 0] * u.mas, contrast=0.1, frame="sky",
                         pixscale=10 * u.mas)
    with pytest.raises(KpifsError, match="contrasts must be finite"):
        inject_companion(cube, position=[30, 0] * u.mas, contrast=-1, pixscale=10 * u.mas)
    with pytest.raises(KpifsError, match="two finite offsets"):
        inject_companion(cube, position=[30] * u.mas, contrast=0.1, pixscale=10 * u.mas)


def test_inject_command(tmp_path, capsys):
    assert main(["simulate", "--preset", "paper", "--frames", "3", "--contrasts", "0,0,0",
                 "-q", "-o", str(tmp_path / "sim")]) == 0
    src = tmp_path / "sim" / "target.fits"
    before = hashlib.sha256(src.read_bytes()).hexdigest()
    out = tmp_path / "inj.fits"
    assert main(["inject", str(src), "--position", "52.1,-31.26mas", "--contrast",
                 "0.01,0.02,0.03", "-o", str(out)]) == 0
    assert hashlib.sha256(src.read_bytes()).hexdigest() == before
    with fits.open(out) as h, fits.open(src) as s:
        hdr = h[0].header
        assert (hdr["INJPOS1"], hdr["INJC3"], hdr["INJFRAME"]) == (52.1, 0.03, "detector")
        diff = h[0].data.astype(float) - s[0].data.astype(float)
    # the companion is the frame shifted by (5, -3) pixels of 10.42 mas, scaled per channel
    peak = np.unravel_index(np.argmax(diff[0, 2]), diff.shape[2:])
    star = np.unravel_index(np.argmax(fits.getdata(src)[0, 2]), diff.shape[2:])
    assert (peak[0] - star[0], peak[1] - star[1]) == (-3, 5)
    assert main(["inject", str(src), "--position", "52mas", "--contrast", "0.01", "-o",
                 str(tmp_path / "x.fits")]) == 2
    assert main(["inject", str(src), "--contrast", "0.01", "-o", str(out)]) == 2
    assert "exists" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore:.*too few frames")
def test_injection_curve_with_one_separation(tmp_path, capsys):
    """One separation (as the docs' per-separation PHARO commands give) is a curve of one
    point, in the library and on the command line (was a TypeError)."""
    assert main(["simulate", "--preset", "paper", "--frames", "6", "--contrasts", "0,0,0",
                 "--shape", "48", "-q", "-o", str(tmp_path / "sim")]) == 0
    out = tmp_path / "curve.fits"
    assert main(["inject", str(tmp_path / "sim" / "target.fits"), "--calibrator",
                 str(tmp_path / "sim" / "calibrator.fits"), "--curve", "--separations",
                 "80mas", "--contrasts", "0.05", "--angles", "1", "--draws", "1000",
                 "--step", "0.8m", "-q", "-o", str(out)]) == 0
    printed = capsys.readouterr()
    assert "80 mas: injections" in printed.out
    assert "HIERARCH" not in printed.err and "truncated" not in printed.err   # plain cards
    with fits.open(out) as h:
        assert len(h["INJECTIONS"].data) == 1 and len(h["LIMITS"].data) == 1
        assert h["INJECTIONS"].data["n_injected"][0] == 1
        assert h["INJECTIONS"].header["NANGLES"] == 1 and h["INJECTIONS"].header["PFA"] == 1e-3
    from kpifs import KernelModel, extract_kernel_phases, make_pupil
    from kpifs.inject import injection_limits
    from kpifs.io import read_cube
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    cubes = {}
    for role in ("target", "calibrator"):
        with read_cube(tmp_path / "sim" / f"{role}.fits") as cube:
            args = dict(wavelengths=cube.wavelengths, pixscale=cube.pixscale)
            cubes[role] = np.array(cube.data, float)
    cal = extract_kernel_phases(cubes["calibrator"], km, **args)
    tab = injection_limits(cubes["target"], [cal], km, window=cal.window, **args,
                           separations=80 * u.mas, contrasts=0.05, n_angles=1, n_draws=1000)
    assert len(tab) == 1 and len(tab.meta["limits"]) == 1


def test_flux_falling_off_the_image_is_stated_or_refused():
    """Three equal point sources; a 6-pixel shift moves one off the 32-pixel image: a third
    of the companion's flux is lost (said), and a shift off the image is refused."""
    cube = np.zeros((1, 1, 32, 32))
    cube[0, 0, 16, [4, 16, 28]] = 1.0
    with pytest.warns(KpifsWarning, match=r"33% of the flux of the companion at \(60, 0\) mas"):
        out = inject_companion(cube, position=[60, 0] * u.mas, contrast=0.1,
                               pixscale=10 * u.mas)
    assert out.sum() - cube.sum() == pytest.approx(0.2, abs=1e-9)      # two of three land
    with pytest.raises(KpifsError, match="falls off the image: 100% of its flux would be"):
        inject_companion(cube, position=[0, 400] * u.mas, contrast=0.1, pixscale=10 * u.mas)
    with pytest.raises(KpifsError, match="2 contrasts for 1 channel"):
        inject_companion(cube, position=[10, 0] * u.mas, contrast=[0.1, 0.2],
                         pixscale=10 * u.mas)
    with pytest.raises(KpifsError, match=r"in \[0, 1\)"):
        inject_companion(cube, position=[10, 0] * u.mas, contrast=1.5, pixscale=10 * u.mas)


def test_limit_is_interpolated_or_censored():
    from kpifs.inject import _limit, _next_contrast
    c = [1e-3, 2e-3, 4e-3]
    assert _limit(c, [1.0, 1.0, 1.0], 0.5) == (1e-3, "<")      # an upper bound
    assert _limit(c, [0.0, 0.25, 0.25], 0.5) == (4e-3, ">")    # a lower bound
    assert _limit(c, [0.0, 0.5, 1.0], 0.5) == (pytest.approx(2e-3, rel=1e-12), "=")
    # halfway from 0.25 to 0.75 in found fraction: halfway from 2e-3 to 4e-3 in log contrast
    lim, flag = _limit(c, [0.0, 0.25, 0.75], 0.5)
    assert flag == "=" and lim == pytest.approx(2e-3 * np.sqrt(2), rel=1e-12)
    # a ladder grows below while everything is found, above while nothing is, up to its size
    assert _next_contrast(c, [1.0, 1.0, 1.0], 0.5, 8) == pytest.approx(5e-4)
    assert _next_contrast(c, [0.0, 0.0, 0.25], 0.5, 8) == pytest.approx(8e-3)
    assert _next_contrast(c, [0.0, 0.5, 1.0], 0.5, 8) is None
    assert _next_contrast(c, [1.0, 1.0, 1.0], 0.5, 3) is None


@pytest.mark.filterwarnings("ignore:.*too few frames")
def test_adaptive_ladder_brackets_the_limit(tmp_path):
    """Started 8 times too high, the ladder steps down by itself until it brackets the
    50 % level; with too few steps allowed the limit is reported as a bound."""
    from kpifs import KernelModel, extract_kernel_phases, make_pupil
    from kpifs.inject import injection_limits
    from kpifs.simulation.simulate import simulate_scene
    obs = simulate_scene("paper", n_frames=24, seed=3, npup=32, contrasts=0.0, shape=(40, 40))
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.8 * u.m))
    args = dict(wavelengths=obs.wavelengths, pixscale=obs.params.pixscale)
    cal = extract_kernel_phases(obs.calibrator, km, **args)
    kw = dict(window=cal.window, separations=[80] * u.mas, n_angles=2, n_draws=1000, **args)
    # the analytic limit at 80 mas is 2e-3 here
    tab = injection_limits(obs.target, [cal], km, start=0.016, **kw)
    c, p = np.asarray(tab["contrast"]), np.asarray(tab["pd"])
    assert tab.meta["flags"] == ["="] and tab.meta["ladder"] == "adaptive"
    assert c.min() < 0.004 and len(c) > 3            # it went below the first steps
    assert p[0] < 0.5 <= p[-1]                         # bracketed
    assert c[0] < tab.meta["limits"][0] < c[-1]
    short = injection_limits(obs.target, [cal], km, start=0.016, max_steps=3, **kw)
    assert short.meta["flags"] == ["<"] and short.meta["limits"] == [pytest.approx(0.008)]

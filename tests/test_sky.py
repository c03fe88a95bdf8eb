"""Companions on the sky: the detector/sky convention, PA bins, and the fit of a
rotating sequence read from xara- and jwst-kpi-layout files."""
import warnings

import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, KpifsError, KpifsWarning, make_pupil
from kpifs.detect.fit import fit_binary
from kpifs.detect.sky import (detector_to_sky, pa_bins, rotated_binary_kernel_phases,
                              separation_pa, sky_to_detector)

from kpfits_layouts import parts_of, write_jwstkpi, write_xara
from kpfits_layouts import sky_to_detector as layouts_sky_to_detector


@pytest.fixture(scope="module")
def km():
    return KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m, grey=False))


def test_convention_matches_angles_module_and_layouts():
    rng = np.random.default_rng(1)
    dra, ddec, t = rng.normal(size=(3, 50)) * [[100], [100], [90]]
    x, y = sky_to_detector(dra, ddec, t)
    np.testing.assert_allclose((x, y), layouts_sky_to_detector(dra, ddec, t), atol=1e-12)
    np.testing.assert_allclose(detector_to_sky(x, y, t), (dra, ddec), atol=1e-12)
    # PA on the sky = PA on the detector (East of +y, i.e. atan2(-x, y)) + DETPA
    pa_det = np.rad2deg(np.arctan2(-x, y))
    sep, pa = separation_pa(dra, ddec)
    np.testing.assert_allclose((pa - pa_det - t + 180) % 360 - 180, 0, atol=1e-9)
    np.testing.assert_allclose(sep, np.hypot(x, y))
    # DETPA = 0: North up, East left
    assert sky_to_detector(1.0, 0.0, 0.0) == pytest.approx((-1.0, 0.0))
    assert separation_pa(0.0, -2.0)[1] == pytest.approx(180.0)


def test_pa_bins_widths_and_wrap():
    kw = dict(max_separation=300 * u.mas, wavelength_min=2.0 * u.um, baseline_max=8 * u.m)
    a, w = pa_bins(np.linspace(0, 40, 401), **kw)
    # finest fringe 51.6 mas; 2 % of it at 300 mas: 0.197 deg bins -> 204 bins
    assert a.size == 204 and w.sum() == pytest.approx(1.0)
    assert np.average(a, weights=w) == pytest.approx(20.0)
    a, w = pa_bins([359.99, 0.01], **kw)                     # across 0/360: one bin
    assert a.size == 1 and a[0] == pytest.approx(360.0)
    with pytest.raises(KpifsError, match="finite"):
        pa_bins([0.0, np.nan], **kw)


def test_single_angle_fit_is_the_detector_fit_rotated(km):
    wl = [1.6, 1.7] * u.um
    t = 33.0
    x, y = sky_to_detector(-60.0, 80.0, t)
    kp = km.binary_kernel_phases([x, y] * u.mas, [8e-3, 6e-3], wl)
    w = np.repeat(np.eye(km.n_kp)[None] * 1e3, 2, axis=0)
    det = fit_binary(kp, w, km, wl, (x + 3, y - 3), [5e-3, 5e-3])
    sky = fit_binary(kp, w, km, wl, tuple(np.add(detector_to_sky(x + 3, y - 3, t), 0)),
                     [5e-3, 5e-3], detpa=[t])
    assert det["frame"] == "detector" and sky["frame"] == "sky"
    np.testing.assert_allclose(detector_to_sky(det["x"], det["y"], t), (sky["x"], sky["y"]),
                               atol=1e-5)
    assert (sky["x"], sky["y"]) == pytest.approx((-60.0, 80.0), abs=1e-4)
    np.testing.assert_allclose(sky["contrast"], det["contrast"], rtol=1e-6)
    assert sky["x_err"] ** 2 + sky["y_err"] ** 2 == pytest.approx(
        det["x_err"] ** 2 + det["y_err"] ** 2, rel=1e-4)


def _rotating_sequence(km, wl, sep, pa, contrast, detpa, sigma, seed):
    dra, ddec = sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa))
    rng = np.random.default_rng(seed)
    kp = np.stack([km.binary_kernel_phases(list(sky_to_detector(dra, ddec, t)) * u.mas,
                                           contrast, wl) for t in detpa])
    return kp + sigma * rng.normal(size=kp.shape)


def _target_and_calibrator(detpa, seeds, sep=120.0, pa=145.0, c=0.03):
    """Kernel phases of a companion fixed on the sky and of a calibrator, frames at *detpa*
    (1 m binary Subaru model, three channels, 0.01 rad of noise a frame)."""
    km1 = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m, grey=False))
    wl = [1.55, 1.65, 1.75] * u.um
    return [KernelPhaseData(_rotating_sequence(km1, wl, sep, pa, cc, detpa, 0.01, seed=s), wl,
                            10 * u.mas, km1, detpa=detpa) for cc, s in zip((c, 0.0), seeds)]


def _fit_sky(kpd, sigma, start, c0):
    """Fit the frame-averaged kernel phases of a file with the rotating model."""
    kp = kpd.kp.mean(axis=0)
    q = kp.shape[0]
    w = np.repeat(np.eye(kpd.n_kp)[None], q, axis=0) / (sigma / np.sqrt(kpd.n_frame))
    ang, aw = pa_bins(kpd.detpa, max_separation=400 * u.mas,
                      wavelength_min=kpd.wavelengths.min(),
                      baseline_max=kpd.kernel_model.baseline_length.max())
    r = fit_binary(kp, w, kpd.kernel_model, kpd.wavelengths, start, [c0] * q,
                   detpa=ang, detpa_weights=aw, bounds_mas=40.0)
    return r, separation_pa(r["x"], r["y"])


@pytest.mark.parametrize("layout", ["xara", "jwst-kpi"])
def test_rotating_sequence_recovered_on_the_sky(km, tmp_path, layout):
    wl = [1.55, 1.65, 1.75] * u.um
    detpa = np.linspace(95.0, 135.0, 20)                          # 40 deg of rotation
    sep, pa, c = 150.0, 145.0, 0.02
    kp = _rotating_sequence(km, wl, sep, pa, c, detpa, 0.01, seed=4)
    p = parts_of(KernelPhaseData(kp, wl, 12 * u.mas, km))
    if layout == "xara":
        path = write_xara(tmp_path / "x.fits", p, detpa=detpa)
    else:
        path = write_jwstkpi(tmp_path / "j.fits", p, detpa=detpa)
    kpd = KernelPhaseData.read(path)
    np.testing.assert_allclose(kpd.detpa, detpa)
    # start 10 mas and 4 deg away from the truth
    s = np.array([np.sin(np.deg2rad(pa - 4)), np.cos(np.deg2rad(pa - 4))]) * (sep + 10)
    r, (fsep, fpa) = _fit_sky(kpd, 0.01, tuple(s), 0.01)
    assert r["success"] and r["frame"] == "sky"
    assert abs(fpa - pa) < 1.0 and abs(fsep / sep - 1) < 0.01
    assert np.all(np.abs(r["contrast"] / c - 1) < 0.1)
    # the same data fitted as if the detector did not rotate (mean angle) is worse
    bad = fit_binary(kpd.kp.mean(axis=0),
                     np.repeat(np.eye(kpd.n_kp)[None], kpd.n_wave, axis=0) / (0.01 / np.sqrt(20)),
                     km, kpd.wavelengths, tuple(s), [0.01] * kpd.n_wave, detpa=[detpa.mean()],
                     bounds_mas=40.0)
    assert bad["chi2"] > 1.5 * r["chi2"]


def test_nirc2_like_xara_binary_on_the_sky(km, tmp_path):
    """A xara-written single-channel file of a wide binary (330 mas, 0.054, PA 145)."""
    wl = [2.12] * u.um
    detpa = np.linspace(200.0, 215.0, 12)
    kp = _rotating_sequence(km, wl, 330.0, 145.0, 0.054, detpa, 0.02, seed=9)
    path = write_xara(tmp_path / "nirc2.fits", parts_of(KernelPhaseData(kp, wl, 10 * u.mas, km)),
                      detpa=detpa)
    kpd = KernelPhaseData.read(path)
    assert kpd.meta["layout"] == "xara" and kpd.n_frame == 12
    s = 320 * np.array([np.sin(np.deg2rad(142)), np.cos(np.deg2rad(142))])
    r, (fsep, fpa) = _fit_sky(kpd, 0.02, tuple(s), 0.03)
    assert fsep == pytest.approx(330.0, rel=0.01) and abs(fpa - 145.0) < 1.0
    assert r["contrast"][0] == pytest.approx(0.054, rel=0.1)


def test_rotated_model_is_the_frame_mean(km):
    wl = [1.6] * u.um
    ang = [10.0, 20.0, 50.0]
    m = rotated_binary_kernel_phases(km, [40, -70] * u.mas, 0.01, wl, ang, [1, 2, 1])
    ref = sum(wt * km.binary_kernel_phases(list(sky_to_detector(40, -70, t)) * u.mas, 0.01, wl)
              for t, wt in zip(ang, [0.25, 0.5, 0.25]))
    np.testing.assert_allclose(m, ref, atol=1e-14)


@pytest.mark.filterwarnings("ignore::kpifs.KpifsWarning")
def test_cli_detect_reports_a_xara_binary_on_the_sky(km, tmp_path, capsys):
    """`kpifs detect` on xara-written NIRC2-like files (target and calibrator, one
    channel, 160 frames at DETPA 207 deg): the companion at 330 mas, PA 145 deg."""
    from astropy.io import fits
    from kpifs.cli import main
    wl = [2.12] * u.um
    detpa = np.full(160, 207.0)
    tgt = _rotating_sequence(km, wl, 330.0, 145.0, 0.054, detpa, 0.02, seed=11)
    cal = _rotating_sequence(km, wl, 330.0, 145.0, 0.0, detpa, 0.02, seed=12)
    paths = [write_xara(tmp_path / f"{n}.fits",
                        parts_of(KernelPhaseData(k, wl, 10 * u.mas, km)), detpa=detpa)
             for n, k in (("t", tgt), ("c", cal))]
    out = tmp_path / "det.fits"
    rc = main(["detect", str(paths[0]), "--calibrator", str(paths[1]), "--pfa", "1e-3",
               "--max-sep", "360mas", "-o", str(out)])
    text = capsys.readouterr()
    assert rc == 0, text.err
    text = text.out
    assert "East of North" in text
    with fits.open(out) as h:
        assert h[0].header["DETPA"] == pytest.approx(207.0)
        cand = h["CANDIDATES"].data
        assert len(cand) >= 1
        assert cand["fit_separation"][0] == pytest.approx(330.0, rel=0.01)
        assert abs(cand["fit_pa_sky"][0] - 145.0) < 1.0
        assert cand["fit_dra"][0] == pytest.approx(330 * np.sin(np.deg2rad(145)), abs=3)


@pytest.mark.filterwarnings("ignore::kpifs.KpifsWarning")
@pytest.mark.parametrize("via_file", [False, True], ids=["memory", "kpfits"])
def test_detect_refits_a_rotating_sequence_on_the_sky(tmp_path, via_file):
    """Calibration passes the frames' angles on (in memory, or through the calibrated
    KPFITS's DETPA-FR); detect refits the companion with the rotating model: PA within
    1 deg, separation within 1 % (40 deg of rotation)."""
    from kpifs.calibration.calibrate import calibrate
    from kpifs.data import DetectionGrid
    from kpifs.detect import detect
    n = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m, grey=False)).n_kp + 30
    detpa = np.linspace(100.0, 140.0, n)
    sep, pa = 120.0, 145.0
    tgt, cal = _target_and_calibrator(detpa, (21, 22), sep, pa)
    kpd = calibrate(tgt, [cal])
    if via_file:
        kpd = KernelPhaseData.read(kpd.write(tmp_path / "cal.fits"))
        np.testing.assert_allclose(kpd.meta["detpa_frames"], detpa)
    assert len(kpd.meta["detpa_frames"]) == n
    grid = DetectionGrid.from_separation(150 * u.mas, 8 * u.mas, min_sep=30 * u.mas)
    res = detect(kpd, grid=grid, n_draws=2000, seed=0, max_candidates=1)
    row = res.candidates[0]
    assert "rotating model" in res.candidates.meta["sky_fit"]
    assert abs(row["fit_pa_sky"].to_value(u.deg) - pa) < 1.0
    assert row["fit_separation"].to_value(u.mas) == pytest.approx(sep, rel=0.01)
    # the detector fit rotated by the mean angle is biased by the smearing (2.1 deg with the
    # out-of-sample error model, over 5 with the earlier one), the rotating refit is not
    _, pa_mean = separation_pa(*detector_to_sky(row["fit_x"].value, row["fit_y"].value,
                                                res.candidates.meta["detpa"]))
    assert abs(pa_mean - pa) > 1.5
    assert np.all(np.isfinite([row["fit_dra_err"].value, row["fit_pa_sky_err"].value]))


@pytest.mark.parametrize("rotating", [False, True])
def test_analytic_jacobian_matches_finite_differences(km, rotating):
    """fit_binary's analytic Jacobian: same optimum and same (Jacobian-based) errors as
    scipy's 3-point finite differences, with the extraction window and with rotation."""
    from kpifs.model.window import ExtractionWindow
    wl = [1.55, 1.7] * u.um
    rng = np.random.default_rng(5)
    kw = {}
    if rotating:
        ang = np.array([10.0, 25.0, 40.0])
        kw = dict(detpa=ang, detpa_weights=[1, 2, 1])
        kp = rotated_binary_kernel_phases(km, [50, -70] * u.mas, [0.02, 0.015], wl, ang,
                                          [1, 2, 1])
    else:
        kp = km.binary_kernel_phases([50, -70] * u.mas, [0.02, 0.015], wl)
    kp = kp + rng.normal(0, 0.01, kp.shape)
    w = np.repeat(np.eye(km.n_kp)[None], 2, axis=0) * 100
    extra = dict(pixscale=10 * u.mas, window=ExtractionWindow(size=40, radius=12.0))
    a = fit_binary(kp, w, km, wl, (45.0, -65.0), [0.01, 0.01], **kw, **extra)
    b = fit_binary(kp, w, km, wl, (45.0, -65.0), [0.01, 0.01], jacobian="3-point",
                   **kw, **extra)
    for k in ("x", "y"):
        assert a[k] == pytest.approx(b[k], abs=1e-4)
    for k in ("x_err", "y_err"):
        assert a[k] == pytest.approx(b[k], rel=1e-4)
    np.testing.assert_allclose(a["contrast_err"], b["contrast_err"], rtol=1e-4)
    assert abs(a["x"] - 50) < 5 * a["x_err"] and abs(a["y"] + 70) < 5 * a["y_err"]
    with pytest.raises(KpifsError, match="jacobian"):
        fit_binary(kp, w, km, wl, (45.0, -65.0), [0.01, 0.01], jacobian="exact")


@pytest.fixture(scope="module")
def rotating_search(tmp_path_factory):
    """A companion fixed on the sky (sep 120 mas, PA 145 deg) in a sequence turning by 60
    deg, calibrated, searched on the sky (auto) and on the detector."""
    from kpifs.calibration.calibrate import calibrate
    from kpifs.detect import detect
    n = KernelModel.from_pupil(make_pupil("subaru", step=1.0 * u.m, grey=False)).n_kp + 30
    detpa = np.linspace(80.0, 140.0, n)
    sep, pa = 120.0, 145.0
    tgt, cal = _target_and_calibrator(detpa, (31, 32), sep, pa)
    with pytest.warns(Warning, match="a search on the sky .* turns the model"):
        kpd = calibrate(tgt, [cal])
    kw = dict(n_draws=2000, seed=0, max_candidates=2)
    sky = detect(kpd, **kw)
    assert len(sky.candidates) == 1
    with warnings.catch_warnings():       # smeared: side peaks beyond max_candidates
        warnings.simplefilter("ignore")
        det = detect(kpd, frame="detector", **kw)
    path = sky.write(tmp_path_factory.mktemp("skymap") / "sky.fits")
    return {"sky": sky, "detector": det, "truth": (sep, pa), "path": path}


def test_search_on_the_sky_finds_a_rotating_companion(rotating_search):
    """On the sky the model turns frame by frame: the companion is found where it is, with
    a higher statistic than the detector search, whose map smears it along the arc."""
    sky, det = rotating_search["sky"], rotating_search["detector"]
    sep, pa = rotating_search["truth"]
    assert sky.meta["frame"] == "sky" and det.meta["frame"] == "detector"
    assert sky.grid.frame == "sky" and sky.grid.x[0] > sky.grid.x[-1]     # East left
    row = sky.candidates[0]
    assert abs(row["fit_pa_sky"].to_value(u.deg) - pa) < 1.0
    assert row["fit_separation"].to_value(u.mas) == pytest.approx(sep, rel=0.01)
    # the grid peak itself is within a grid step of the truth, on the sky
    dra, ddec = sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa))
    assert np.hypot(row["dra"].value - dra, row["ddec"].value - ddec) < abs(sky.grid.step[0])
    assert "rotating model" in sky.candidates.meta["sky_fit"]
    assert sky.candidates["statistic"][0] > 1.5 * det.candidates["statistic"][0]


def test_sky_maps_carry_a_celestial_wcs(rotating_search):
    from astropy.io import fits
    from astropy.wcs import WCS
    from kpifs.data import DetectionResult
    sky = rotating_search["sky"]
    with fits.open(rotating_search["path"]) as h:
        hdr = h["DETECTION"].header
        assert (hdr["CTYPE1"], hdr["CTYPE2"]) == ("RA---TAN", "DEC--TAN")
        assert hdr["CDELT1"] < 0 < hdr["CDELT2"] and h[0].header["GRIDFRM"] == "sky"
        w = WCS(hdr)
        stat = h["DETECTION"].data
    # the map's brightest pixel, through the WCS, is the candidate's grid position
    iy, ix = np.unravel_index(np.nanargmax(stat), stat.shape)
    world = w.pixel_to_world(ix, iy)
    star = w.pixel_to_world(*(w.wcs.crpix - 1))
    off_ra, off_dec = star.spherical_offsets_to(world)
    row = sky.candidates[0]
    assert off_ra.to_value(u.mas) == pytest.approx(row["dra"].value, abs=1e-6)
    assert off_dec.to_value(u.mas) == pytest.approx(row["ddec"].value, abs=1e-6)
    back = DetectionResult.read(rotating_search["path"])
    assert back.grid.frame == "sky"
    np.testing.assert_allclose(back.grid.x, sky.grid.x, atol=1e-9)
    np.testing.assert_allclose(back.grid.y, sky.grid.y, atol=1e-9)


def test_sky_search_needs_known_angles(km):
    from kpifs.detect import detect
    wl = [1.6] * u.um
    kpd = KernelPhaseData(np.zeros((1, 1, km.n_kp)), wl, 10 * u.mas, km,
                          covariance=np.eye(km.n_kp)[None] * 1e-4, meta={"calibrated": True})
    with pytest.raises(KpifsError, match="detector position angle of every frame"):
        detect(kpd, frame="sky", n_draws=1000)
    with pytest.warns(KpifsWarning, match="noise scale clamped"):    # zeros: said (issue 37)
        assert detect(kpd, n_draws=1000).meta["frame"] == "detector"

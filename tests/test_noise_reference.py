"""The map's noise is read against what the null's covariance rows give it (issue 39).

Where the rows the Monte-Carlo null draws from hold more than the whitening along
companions' signatures (20 frames for hundreds of kernel phases, whitened by a
shrunk covariance: the spectral-differential search with no calibrator), the
threshold already holds that excess; the noise scale must not count it twice.
"""
import numpy as np
import pytest
import astropy.units as u

from kpifs import KernelModel, KernelPhaseData, make_pupil
from kpifs.data import DetectionGrid
from kpifs.detect import DetectionModel, detect
from kpifs.detect.channels import combined_scale, map_expectation, map_noise

N_ROWS = 6


@pytest.fixture(scope="module")
def setup():
    km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    wl = [1.6] * u.um
    grid = DetectionGrid.from_separation(80 * u.mas, 10 * u.mas, min_sep=30 * u.mas)
    # rows along the leading directions of companions' signatures on the grid, of total
    # variance the whitening's (the identity): the energy per degree of freedom is 1,
    # the map's expectation far above it
    sig = np.stack([np.asarray(km.binary_kernel_phases([x, y] * u.mas, [1.0], wl))[0]
                    for x, y in zip(grid.X[grid.valid], grid.Y[grid.valid])])
    sig /= np.linalg.norm(sig, axis=1)[:, None]
    lead = np.linalg.svd(sig, full_matrices=False)[2][:N_ROWS]
    rows = (lead * np.sqrt(km.n_kp / N_ROWS))[:, None, :]                  # (6, 1, p)
    model = DetectionModel(km, wl, np.eye(km.n_kp)[None], grid)
    model.correlate(rows)
    return km, wl, grid, rows, model


def test_combined_scale_reads_the_map_against_its_expectation():
    # a map of 6 where the rows give it 5 on average: 1.2, not 6
    assert combined_scale(1.0, 0.1, 6.0, 3.0, 5.0) == pytest.approx(1.2)
    assert combined_scale(1.0, 0.1, 6.0, 3.0) == pytest.approx(6.0)       # rows of unit scale
    assert combined_scale(1.5, 0.1, 6.0, 3.0, 5.0) == pytest.approx(1.5)  # the energy's
    # rows holding less than the whitening: the whitening stays the reference
    assert combined_scale(1.0, 0.1, 1.3, 0.5, 0.23) == pytest.approx(1.3)


def test_map_expectation_is_the_mean_of_map_noise_under_the_rows(setup):
    """Theory: the map's mean square averages to the rows' expectation (here 2000 draws;
    the tolerance is 5 standard errors of their mean)."""
    km, wl, grid, rows, model = setup
    expect = map_expectation(model)
    assert expect > 6                          # the rows concentrate on the signatures
    rng = np.random.default_rng(3)
    vals = np.array([map_noise(model, np.tensordot(rng.standard_normal(N_ROWS), rows, axes=1))
                     for _ in range(2000)])
    assert abs(vals.mean() - expect) < 5 * vals.std() / np.sqrt(len(vals))
    white = np.eye(km.n_kp)[:, None]           # rows whitened by their own covariance: 1
    m2 = DetectionModel(km, wl, np.eye(km.n_kp)[None], grid)
    m2.correlate(white)
    assert map_expectation(m2) == pytest.approx(1.0, abs=1e-6)


def test_noise_scale_does_not_count_the_rows_excess_twice(setup):
    """Data drawn from the rows themselves: the map reads several times 1, the rows
    expect as much, and the noise scale stays of order 1 (it was the map's value)."""
    km, wl, grid, rows, model = setup
    rng = np.random.default_rng(7)
    scales, kappas, maps, expects = [], [], [], []
    for _ in range(12):
        y = np.tensordot(rng.standard_normal(N_ROWS), rows, axes=1)[None]
        kpd = KernelPhaseData(y, wl, 16.2 * u.mas, km, covariance=np.eye(km.n_kp)[None],
                              covariance_rows=rows, meta={"calibrated": True})
        res = detect(kpd, pfa=1e-2, n_draws=1000, seed=1, grid=grid, limits=False, fit=False)
        scales.append(res.meta["noise_scale"])
        kappas.append(res.meta["chi2_red"])
        maps.append(res.energy["map_noise"])
        expects.append(res.energy["map_expectation"])
    assert np.allclose(expects, map_expectation(model)) and expects[0] > 6
    scales, kappas, ratio = np.asarray(scales), np.asarray(kappas), np.divide(maps, expects)
    # the map reads several times 1 (its mean over 12 draws near its expectation)...
    assert np.mean(maps) > 0.5 * expects[0]
    # ...and the scale is the larger of the energy's and the map's ratio to what the rows
    # give it (1 where both are below 1 and not confidently so), not the map itself
    up = np.maximum(kappas, ratio)
    np.testing.assert_allclose(scales[up >= 1], up[up >= 1], rtol=1e-9)
    assert np.all(scales[up < 1] <= 1.0)
    assert np.median(scales) < 0.2 * np.median(maps)

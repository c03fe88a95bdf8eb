"""The binary tests' compiled loops (kpifs/detect/_kernels.c) against their numpy twins,
and the null's all-channels route against its channel-by-channel one."""
import shutil
import sysconfig

import astropy.units as u
import numpy as np
import pytest

from kpifs import KernelModel, make_pupil
from kpifs.data import DetectionGrid
from kpifs.detect import DetectionModel, NullCalibration
from kpifs.detect import _elementwise as ew
from kpifs.detect.null import _CACHE
from kpifs.detect.statistics import binary as binary_module

compiled = pytest.mark.skipif(ew._kernels is None, reason="the C extension is not built")


@pytest.fixture
def numpy_only(monkeypatch):
    """The numpy loops, as where the extension is not built."""
    monkeypatch.setattr(ew, "COMPILED", False)


def _awkward(shape, seed):
    """float32 draws with the values where clipping is delicate: signed zeros, NaN, inf,
    denormals and ties."""
    z = np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
    flat = z.reshape(-1)
    flat[:7] = [0.0, -0.0, np.nan, np.inf, -np.inf, 1e-42, -1e-42]
    flat[7:11] = 1.0
    return z


def test_the_extension_is_built_where_it_can_be():
    # a machine with a C compiler builds it (pip install); where none is found, numpy runs
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc) is None:
        pytest.skip(f"no C compiler ({cc}): kpifs runs its numpy loops")
    assert ew._kernels is not None, (
        "kpifs.detect._kernels was not built although a C compiler is here: "
        "reinstall (pip install -e .) to build it")


@compiled
@pytest.mark.parametrize("present", [(1, 1, 1), (0, 1, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1)])
def test_binary_forms_compiled_equals_numpy_bit_for_bit(present):
    z = _awkward((40, 301), 1)
    start = np.random.default_rng(2).random((3, 40, 301)).astype(np.float32)
    runs = []
    for compiled_ in (True, False):
        acc = [s.copy() if keep else None for s, keep in zip(start, present)]
        ew.COMPILED, saved = compiled_, ew.COMPILED
        try:
            ew.binary_forms(z, *acc)
        finally:
            ew.COMPILED = saved
        runs.append(acc)
    for a, b in zip(*runs):
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a, b, equal_nan=True)
            assert a.tobytes() == b.tobytes() or np.isnan(a).any()


@compiled
@pytest.mark.parametrize("with_tot", [True, False])
def test_binary_maxima_compiled_equals_numpy_bit_for_bit(with_tot, monkeypatch):
    z = _awkward((13, 22, 530), 3)
    z[5] = np.abs(z[5])                    # a draw without NaN: its maxima are numbers
    tot = np.random.default_rng(4).standard_normal((13, 530)).astype(np.float32) \
        if with_tot else None
    fast = ew.binary_maxima(z, tot)
    monkeypatch.setattr(ew, "COMPILED", False)
    slow = ew.binary_maxima(z, tot)
    assert np.array_equal(fast, slow, equal_nan=True)
    assert np.all(np.isfinite(fast[5, :3]))
    if not with_tot:
        assert np.all(fast[:, 3] == -np.inf)


def test_binary_maxima_is_what_it_says():
    rng = np.random.default_rng(5)
    z = rng.standard_normal((6, 4, 50)).astype(np.float32)
    tot = rng.standard_normal((6, 50)).astype(np.float32)
    out = ew.binary_maxima(z, tot)
    zz = z.astype(float)
    pos = np.maximum(zz, 0).sum(axis=1)
    assert np.allclose(out[:, 0], (np.maximum(zz, 0) ** 2).sum(axis=1).max(axis=1), rtol=1e-5)
    assert np.allclose(out[:, 1], (np.minimum(zz, 0) ** 2).sum(axis=1).max(axis=1), rtol=1e-5)
    assert np.allclose(out[:, 2], pos.max(axis=1), rtol=1e-5)
    assert np.allclose(out[:, 3], (pos - tot).max(axis=1), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("power", [1, 2])
def test_crossing_sums_are_the_newton_sums(power):
    rng = np.random.default_rng(6)
    z = rng.standard_normal((4, 22, 1024)).astype(np.float32)
    m32 = rng.random((4, 22)).astype(np.float32)
    c = (2 * rng.random((4, 1024))).astype(np.float32)
    f, g = ew.crossing_sums(z, m32, c, power)
    u = np.maximum(z.astype(float) + m32[:, :, None] * c[:, None, :].astype(float), 0)
    assert np.allclose(f, (u ** power).sum(axis=1), rtol=1e-5)
    assert np.allclose(g, np.einsum("kq,kqn->kn", m32, u if power == 2 else (u > 0)),
                       rtol=1e-5)


def _null_model():
    km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    grid = DetectionGrid.from_separation(120 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    q = 6
    rows = np.random.default_rng(7).standard_normal((15, q, km.n_kp)) / np.sqrt(15)
    dm = DetectionModel(km, np.linspace(1.5, 1.8, q) * u.um,
                        np.eye(km.n_kp)[None].repeat(q, 0), grid)
    return dm, rows


def _draws(dm, rows):
    _CACHE.clear()
    null = NullCalibration(dm, form="B", n_draws=1000, seed=3, noise_rows=rows,
                           also=("B-paper", "S"))
    out = {f: null.draws if f == "B" else NullCalibration(
        dm, form=f, n_draws=1000, seed=3, noise_rows=rows, also=("B", "S")).draws
        for f in ("B", "B-paper")}
    _CACHE.clear()
    return out


def test_null_draws_without_the_extension_are_the_same(numpy_only):
    dm, rows = _null_model()
    slow = _draws(dm, rows)
    ew.COMPILED = ew._kernels is not None
    fast = _draws(dm, rows)
    for f in slow:
        assert np.array_equal(slow[f], fast[f])


def test_null_draws_all_channels_at_once_as_channel_by_channel(monkeypatch):
    dm, rows = _null_model()
    together = _draws(dm, rows)
    # a reduction without add_channels makes the null project channel by channel
    monkeypatch.delattr(binary_module._Batch, "add_channels")
    apart = _draws(dm, rows)
    for f in together:
        # the same draws; one product for every channel or one each may round differently
        # in some BLAS libraries
        assert np.allclose(together[f], apart[f], rtol=1e-5)
        assert together[f][-1] > together[f][0] > 0


@compiled
@pytest.mark.parametrize("power", [1, 2])
def test_newton_crossings_compiled_as_numpy(power, monkeypatch):
    """The compiled Newton steps stop where numpy's do and land on the same crossings
    (to the steps' tolerance: numpy's sums may fuse multiply-adds on other processors)."""
    from kpifs.detect import limits
    rng = np.random.default_rng(8)
    k, q, n = 9, 22, 512
    z = rng.standard_normal((k, q, n)).astype(np.float32)
    m = rng.random((k, q))
    m[4, 1:] = 0.0                               # a signal in one channel only
    m[5, :10] = 0.0
    threshold = 40.0 if power == 2 else 12.0
    start = limits._draw_starts(z, m, threshold, power)        # as the limits start
    fast = limits._crossings(z, m, threshold, power, start)
    monkeypatch.setattr(ew, "COMPILED", False)
    slow = limits._crossings(z, m, threshold, power, start)
    assert np.allclose(fast, slow, rtol=2e-4, atol=1e-7, equal_nan=True)
    # the crossings are where the statistic reaches the threshold (or 0: above without);
    # the steps come from the right, so one stopped before converging is to its right
    # (piecewise-linear power 1 can need more than its 12 steps: 28 of 4608 draws here)
    c = fast.astype(float)
    t = np.sum(np.maximum(z + c[:, None, :] * m[:, :, None], 0) ** power, axis=1)
    crossed = (c > 0) & np.isfinite(c)
    assert np.all(t[crossed] >= threshold * (1 - 2e-3))
    assert np.mean(np.abs(t[crossed] / threshold - 1) < 2e-3) > 0.98
    t0 = np.sum(np.maximum(z, 0) ** power, axis=1)
    assert np.all(t0[c == 0] >= threshold * (1 - 1e-4))

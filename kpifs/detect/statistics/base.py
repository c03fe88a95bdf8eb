"""`DetectionTest`: what a detection test owns, and what it is given.

A test is an object (`DESIGN.md` §7): its statistic on the whitened data at
every grid position, its law at one known position under H0, what it keeps of
each Monte-Carlo draw of the null (`NullSetup`, a reduction whose maxima over
the grid are the null's draws), how it scales with the noise (*power*), its
detection limit (`LimitInputs`) and its words for printouts, cards and
figures. The registry (`kpifs.detect.statistics.registry`) holds one instance
per name; `kpifs.detect.detect`, the command line, the figures, the products
and `kpifs roc` read it and never spell a test's name.
"""
from dataclasses import dataclass, field

import numpy as np

from .. import _elementwise

__all__ = ["DetectionTest", "NullSetup", "LimitInputs", "KnownPositionDraws", "TILE"]

#: Draws per tile of a null reduction's elementwise work (a reduction updates its
#: accumulators tile by tile, so that its work arrays stay in the processor's cache).
TILE = _elementwise.TILE


@dataclass
class KnownPositionDraws:
    """Monte-Carlo draws at one known position, under H0 and H1 (pairs ``(h0, h1)``).

    *ex* ``sum_i e_i x_i`` (plus ``||x||^2`` under H1), *ee* the energy
    ``sum_i ||e_i + x_i||^2``, *z* (n, q) the normalised projections on the
    signal's direction, *norms* (q,) the signal's norm per channel
    (`kpifs.detect.known_position.monte_carlo_roc`).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.statistics import KnownPositionDraws, get_test
    >>> z = np.array([[1.0, -2.0]])
    >>> draws = KnownPositionDraws((None, None), (None, None), (z, z + 1), np.ones(2))
    >>> [float(t[0]) for t in get_test("B").known_position(draws)]
    [1.0, 4.0]
    """

    ex: tuple
    ee: tuple
    z: tuple
    norms: np.ndarray


@dataclass
class NullSetup:
    """What a test's null reduction is built from, once per set of draws.

    *positions* are the flat grid positions projected (half the grid when
    *mirrored*: a signature at ``-pos`` is minus that at ``pos``), *spectrum*
    the matched filter's spectrum shape. *combine*, given channel weights
    (r, q, npos), returns what a draw's ``combined`` turns into the weighted
    channel sums ``sum_i weights[j, i] z_i`` (r, n, npos), one matrix product each,
    or None when the draws are cheaper channel by channel: a reduction that is
    linear in the ``z_i`` takes that route (and sets ``per_channel = False``).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.statistics import NullSetup, get_test
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(60 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6, 1.7] * u.um, np.eye(km.n_kp)[None].repeat(2, 0), grid)
    >>> setup = NullSetup(dm, *dm.half_positions(), names=("B",))
    >>> part = get_test("B").null_reducer(setup).batch(4)
    >>> z = np.ones((4, len(setup.positions)), np.float32)
    >>> part.add(0, z); part.add(1, -z)
    >>> part.finish(None)["B"].tolist()           # 1 at +pos, 1 at the mirror
    [1.0, 1.0, 1.0, 1.0]
    """

    model: object
    positions: np.ndarray
    mirrored: bool
    spectrum: object = None
    #: The names of every test reduced from the same draws (tests that share work).
    names: tuple = ()
    combine: object = None

    @property
    def n_channels(self):
        return len(self.model.wavelengths)


@dataclass
class LimitInputs:
    """What every test's limit is computed from (`DetectionTest.limit`).

    *norm2* (q, ny, nx) are the signatures' squared norms, *spectrum* the
    companion's spectrum shape (q,), *dof* the whitened dimension, *corr* the
    channels' correlation at each position (ny, nx, q, q; None: independent
    channels), *rows* the whitened covariance rows it comes from, *thresholds*
    a function of a test name giving its global threshold at *pfa* (its
    null's), *search* the test the search used and *search_threshold* its
    threshold; *energy_null* the energy's correlated draws
    (`~kpifs.detect.channels.energy_null`) and *energy_threshold* its threshold.
    *shared* holds what several tests compute once (the binary forms'
    correlated draws).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.statistics import LimitInputs, get_test
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(60 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None] * 1e3, grid)
    >>> inputs = LimitInputs(dm, 1e-3, 0.5, np.ones(1), km.n_kp, 0, None, "NP", 4.0)
    >>> lim = get_test("NP").limit(inputs)           # (4 - Q^-1(0.5)) / ||s||
    >>> bool(np.allclose(lim[grid.valid], 4.0 / np.sqrt(dm.norm2[0][grid.valid])))
    True
    """

    model: object
    pfa: float
    pd: float
    spectrum: np.ndarray
    dof: int
    seed: object
    thresholds: object
    search: str
    search_threshold: float
    #: The names of every test whose limit is computed.
    tests: tuple = ()
    corr: np.ndarray = None
    rows: np.ndarray = None
    energy_null: dict = None
    energy_threshold: float = None
    shared: dict = field(default_factory=dict)

    @property
    def norm2(self):
        return self.model.norm2

    @property
    def mirror(self):
        """Whether limits drawn with the correlation exist on half the grid only."""
        return self.corr is not None and self.model.half_positions()[1]

    def once(self, key, compute):
        """``compute()``, done once per search for all the tests that share it."""
        if key not in self.shared:
            self.shared[key] = compute()
        return self.shared[key]


class DetectionTest:
    """A detection test: subclass it, set the class attributes, implement the methods.

    Attributes
    ----------
    name : str
        Its name (``--test NAME``, the TEST card, the ``<name>_median`` columns).
    label : str
        Legend of figures (matplotlib mathtext allowed).
    description : str
        What it is, in words, for the command line's printout.
    power : float
        How the statistic scales with the noise variance (a sum of squares: 1;
        a sum of amplitudes: 0.5): a noise scale ``k`` divides it by ``k**power``.
    map_test : str or None
        The test whose map and null the search uses when this one has no map
        (the energy detector's candidates come from B's map); None: its own.
    subspace_map : bool
        Its map is made of the spectral model's projections, and is judged by
        that map's own noise too (`kpifs.detect.channels.subspace_scale`).
    spectral_null : bool
        Its null depends on the spectrum shape: drawn on its own, not with the
        other tests' (the matched filter).

    Examples
    --------
    >>> from kpifs.detect.statistics import get_test
    >>> test = get_test("B")
    >>> test.name, test.power, test.map_name
    ('B', 1.0, 'B')
    >>> get_test("E").map_name
    'B'
    """

    name = None
    label = None
    description = None
    power = 1.0
    map_test = None
    subspace_map = False
    spectral_null = False

    @property
    def map_name(self):
        """The name of the test whose map the search uses."""
        return self.map_test or self.name

    def __repr__(self):
        return f"<{type(self).__name__} {self.name!r}>"

    def n_params(self, n_channels, n_basis):
        """Parameters of a companion for this test: its offset and contrasts."""
        return 2 + n_channels

    def map_statistic(self, model, z, spectrum):
        """The statistic at every position from the normalised projections *z*
        (..., q, ny, nx) of a `~kpifs.detect.maps.DetectionModel`."""
        raise NotImplementedError(f"test {self.name!r} has no map")

    def local_pfa(self, model, t):
        """False-alarm probability of the local statistic *t* at one known position."""
        raise NotImplementedError(f"test {self.name!r} has no local law")

    def null_reducer(self, setup):
        """A `NullSetup` -> an object whose ``batch(n)`` gives a fresh reduction of *n*
        draws: ``add(i, z)`` for each channel ``i`` (*z* (n, npos) float32, read
        only; not called when the object's ``per_channel`` is False), then
        ``finish(draw)`` -> ``{name: (n,) maxima over the grid}`` (*draw*'s
        ``channel_sum()`` gives the projections' sum over channels, its
        ``combined(mats)`` the weighted sums of `NullSetup`'s *combine*).

        A batch may also have ``add_channels(z, at, draw)``: every channel's
        projections at once, *z* (m, q, npos) float32 for the draws *at* (a slice
        of the batch). Where every reduction that needs the channels has it and the
        draws go through the noise rows, the null makes them in one product by
        sub-batches and calls it instead of ``add`` (the binary forms then keep
        only their grid maxima, ``kpifs.detect._elementwise.binary_maxima``)."""
        raise NotImplementedError(f"test {self.name!r} has no null")

    def limit(self, inputs):
        """The limit map (ny, nx) at unit noise scale from `LimitInputs`, or None."""
        return None

    def scale(self, common, subspace_noise, g2_draws):
        """The noise scale this test is judged with, from the *common* one (the residual's
        energy and map), the subspace map's mean square and a function giving the
        null's draws of it (`~kpifs.detect.null.NullCalibration.noise_draws` ``'G2'``):
        the common one."""
        return common

    def known_position(self, draws):
        """Statistics under H0 and H1 at a known position
        (`kpifs.detect.known_position.monte_carlo_roc`), or None when the test has none."""
        return None

    def theory_pd(self, x, dof, pfa):
        """Theoretical ``P_D(P_FA)`` at a known position for the whitened signal *x* (q, p)
        with *dof* noise dimensions, or None when there is no closed form."""
        return None

    def theory_auc(self, x, dof):
        """Theoretical area under the ROC curve (`theory_pd` integrated), or None."""
        if self.theory_pd(x, dof, 0.5) is None:
            return None
        grid = np.concatenate([np.logspace(-12, -3, 400), np.linspace(1e-3, 1, 4000)[1:]])
        return float(np.trapezoid(self.theory_pd(x, dof, grid), grid))

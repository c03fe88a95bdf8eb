"""``kpifs detect`` on the 20-frame 22-channel CHARIS simulation: this checkout against the
starting commit of issue 38 and against its own null's bare matrix products.

Makes the file as ``bench_detect_process.py`` does (``kpifs simulate --preset charis
--layout charis --frames 20``, then ``kpifs extract --calibrator``), unless ``--cal``
gives it. Then, alternately and ``--repeat`` times each, whole processes:

- ``kpifs detect CAL`` (default options: test auto = S, limits of every test) with
  this checkout and with the baseline (``--baseline-path DIR``; default: the
  starting commit ``--base`` exported with ``git archive`` to a temporary folder);
- the same search without limits (``detect(kpd, limits=False)``, as injections
  run it), a whole process too, for both: there the null reduces only the search's
  test (issue 38 item 3).

Then, in this process, the run's Gaussian and empirical nulls (the test the run
chose, with the tests its limits read; and the search's test alone, as without
limits) against their bare matrix products: the ``(draws, rows) @ (rows,
positions)`` products those tests' reductions need per batch of 256 draws
(`_bare_products`), nothing else, on one BLAS thread as the nulls. Prints
medians of wall and CPU time (user + system: the steadier figure on a shared
machine), their ratios and the load average.
``--threads N`` sets KPIFS_THREADS and OPENBLAS_NUM_THREADS for every process
(1 by default: on a loaded machine, threads only add contention).
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_detect_process import prepare, search_model  # noqa: E402
from bench_process import ROOT  # noqa: E402

NO_LIMITS = ("import sys; from kpifs.data import KernelPhaseData; from kpifs.detect import "
             "detect; detect(KernelPhaseData.read(sys.argv[1]), limits=False)")


def run_once(cmd, env):
    """Wall time, CPU time (user + system) in s and peak memory (MiB) of one process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, cwd=tempfile.gettempdir())
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status):
        raise SystemExit(f"{' '.join(cmd)} failed")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def time_commands(commands, repeat, env):
    """Medians of `run_once` of each command, run in turn (A B C D A B C D ...)."""
    runs = {name: [] for name in commands}
    for _ in range(repeat):
        for name, (cmd, extra) in commands.items():
            runs[name].append(run_once(cmd, dict(env, **(extra or {}))))
    return {k: np.median(np.array(v), axis=0) for k, v in runs.items()}


def export_base(commit):
    """The package at *commit*, exported to a temporary folder (no worktree)."""
    dest = Path(tempfile.mkdtemp(prefix="kpifs-base-"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "kpifs"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def _run_nulls(cal):
    """What the run's nulls are drawn from: the model, the whitened covariance rows and
    time blocks, and the most empirical draws."""
    from kpifs.covariance import whiten
    from kpifs.detect.channels import scale_block_rows
    from kpifs.detect.null import EMPIRICAL_DRAWS
    kpd, w, rank, model = search_model(cal)
    rows = whiten(kpd.covariance_rows, w)
    model.correlate(rows)
    blocks = scale_block_rows(whiten(kpd.block_rows, w), np.atleast_1d(rank))[0]
    return model, rows, blocks, EMPIRICAL_DRAWS


def _bare_products(model, row_sets, tests, batch=256):
    """The nulls' matrix products alone, per draw set and batch of 256 draws: those the
    run's *tests* cannot do without. The binary forms reduce every channel's
    projections (``coef @ proj[i]``, q products); the subspace test its r projections
    (``coef @ sum_i U[j, i] proj[i]``, r products); B-paper on a symmetric grid the
    channels' sum (one product). On one BLAS thread, as the nulls run."""
    from threadpoolctl import threadpool_limits
    positions, mirrored = model.half_positions()
    sub = model.subspace
    sub = sub.reshape(sub.shape[:2] + (-1,))[:, :, positions]
    total = 0.0
    for rows, n_draws in row_sets:
        valid, z = model.row_projections(rows)
        zh = z[np.searchsorted(valid, positions)]                      # (npos, nrow, q)
        proj = np.ascontiguousarray(zh.transpose(2, 1, 0), np.float32)
        mats = np.einsum("jik,kri->jrk", sub, zh).astype(np.float32)
        total_w = proj.sum(axis=0)
        coef = np.random.default_rng(0).standard_normal((n_draws, len(rows)), dtype=np.float32)
        out = np.empty((batch, proj.shape[2]), np.float32)
        with threadpool_limits(limits=1, user_api="blas"):
            t0 = time.process_time()
            for a in range(0, n_draws, batch):
                c = coef[a:a + batch]
                if "B" in tests or "B-paper" in tests:
                    for i in range(len(proj)):
                        np.matmul(c, proj[i], out=out[:len(c)])
                if "S" in tests:
                    np.matmul(c, mats)
                if "B-paper" in tests and mirrored:
                    np.matmul(c, total_w, out=out[:len(c)])
            total += time.process_time() - t0
    return total


def null_versus_products(cal, repeat=3):
    """CPU time of the run's nulls and of their bare products (`_bare_products`), with the
    limits' tests (S, B, B-paper from the same draws) and for the search alone (S)."""
    from kpifs.detect.null import _CACHE, search_null
    model, rows, blocks, _ = _run_nulls(cal)
    out = {}
    for also in (("B", "B-paper", "S"), ()):
        t_null, t_bare = [], []
        for _ in range(repeat):
            _CACHE.clear()
            t0 = time.process_time()
            # the run's search (auto: S) and the nulls its limits read, from the same draws
            null, parts = search_null(model, form="S", noise_rows=rows, block_rows=blocks,
                                      also=also)
            null.threshold(1e-3)
            t_null.append(time.process_time() - t0)
            sets = [(p.noise_rows, p.n_draws) for p in parts.values()]
            t_bare.append(_bare_products(model, sets, also or ("S",)))
        out[also or ("S",)] = float(np.median(t_null)), float(np.median(t_bare))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--cal", help="an existing calibrated CHARIS file")
    ap.add_argument("--base", default="4cb53d9", help="starting commit (default %(default)s)")
    ap.add_argument("--baseline-path", help="a checkout to time instead of --base")
    ap.add_argument("--threads", default="1", help="threads of every process (default 1)")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp())
    cal = Path(args.cal) if args.cal else prepare(tmp)
    base = args.baseline_path or str(export_base(args.base))
    env = dict(os.environ, PYTHONPATH=str(ROOT), KPIFS_THREADS=args.threads,
               OPENBLAS_NUM_THREADS=args.threads, OMP_NUM_THREADS=args.threads)
    cmd = [sys.executable, "-m", "kpifs", "detect", str(cal), "-o", str(tmp / "det.fits"),
           "--overwrite", "-q"]
    quick = [sys.executable, "-c", NO_LIMITS, str(cal)]
    load0 = os.getloadavg()
    commands = {"kpifs detect": (cmd, None),
                "kpifs detect (start of issue 38)": (cmd, {"PYTHONPATH": base}),
                "detect(limits=False)": (quick, None),
                "detect(limits=False) (start of issue 38)": (quick, {"PYTHONPATH": base})}
    med = time_commands(commands, args.repeat, env)
    print(f"{'whole process (median of %d)' % args.repeat:44s} {'wall (s)':>9s} "
          f"{'CPU (s)':>8s} {'peak MiB':>9s}")
    for name, (wall, cpu, peak) in med.items():
        print(f"{name:44s} {wall:9.2f} {cpu:8.2f} {peak:9.0f}")
    a, b, c, d = (med[n] for n in commands)
    print(f"kpifs detect / start: wall {a[0] / b[0]:.2f}, CPU {a[1] / b[1]:.2f} (target <= 0.5); "
          f"without limits: wall {c[0] / d[0]:.2f}, CPU {c[1] / d[1]:.2f}")
    os.environ.update(KPIFS_THREADS=args.threads)
    # this process's BLAS keeps to the threads of the timed processes: otherwise its idle
    # threads' spinning between products is counted in the nulls' CPU time (the S null
    # measured 0.15 s so, 0.08 s on one thread, 2026-12-01)
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=int(args.threads), user_api="blas"):
        nulls = null_versus_products(cal)
    for tests, (t_null, t_bare) in nulls.items():
        print(f"the run's nulls (Gaussian 5000 + empirical draws; {', '.join(tests)}), CPU: "
              f"{t_null:.2f} s; their bare matrix products {t_bare:.2f} s (ratio "
              f"{t_null / t_bare:.1f}, target <= 2)")
    t_bare = next(iter(nulls.values()))[1]
    print(f"kpifs detect's CPU / the bare products of its nulls: {a[1] / t_bare:.1f}")
    print(f"load average (1, 5, 15 min) before: {load0}, after: {os.getloadavg()} on "
          f"{os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``kpifs roc``: the seed paper's ROC experiment, as a table and figures."""
from pathlib import Path

from .._utils import one_blas_thread, write_table
from ..detect.roc import paper_experiment
from ..exceptions import KpifsError
from ..plotting import save_roc_plots


def run(args):
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise KpifsError(f"{out}: exists and is not a directory")
    table_path = out / "roc.ecsv"
    if table_path.exists() and not args.overwrite:
        raise KpifsError(f"{table_path}: output exists; pass --overwrite to replace it")
    with one_blas_thread():      # the simulation's and the draws' small products
        table, curves = paper_experiment(preset=args.preset, n_frames=args.frames,
                                         n_draws=args.draws, seed=args.seed,
                                         progress=not args.quiet)
    out.mkdir(parents=True, exist_ok=True)
    save_roc_plots(curves, out)
    write_table(table, table_path, overwrite=True)
    for row in table:
        if row["channels"] == "all":
            print(f"{row['test']:8s} all channels: AUC {row['auc']:.4f}, P_D(P_FA=0.01) "
                  f"{row['pd']:.3f}")
    print(f"-> {out}/roc.ecsv, roc.png, roc_np_channels.png")
    return 0

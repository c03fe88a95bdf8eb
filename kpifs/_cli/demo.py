"""``kpifs demo``: the whole chain on simulated CHARIS data."""
from ..demo import run_demo


def run(args):
    run_demo(args.output, frames=args.frames, seed=args.seed, overwrite=args.overwrite,
             progress=not args.quiet, draws=args.draws, keep_inputs=args.keep_inputs)
    return 0

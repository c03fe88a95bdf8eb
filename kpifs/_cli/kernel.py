"""``kpifs kernel``: build a kernel model and save it."""
from .._utils import check_output_path
from ..workflow import kernel_model_for
from ._options import extract_options


def run(args):
    check_output_path(args.output, overwrite=args.overwrite)
    km = kernel_model_for(extract_options(args))
    km.write(args.output, overwrite=args.overwrite)
    print(f"{km.pupil.n_sub} sub-apertures, {km.n_uv} uv points, rank {km.rank}, "
          f"{km.n_kp} kernel phases -> {args.output}")
    return 0

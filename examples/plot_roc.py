"""
ROC curves of the detection tests
=================================

The seed paper's experiment on a small run: the Neyman-Pearson test (the
reference), the binary tests in their two forms and the energy detector, on
all channels; dashed lines are the theory for NP and E.
"""
import matplotlib.pyplot as plt

from kpifs.detect.roc import paper_experiment
from kpifs.plotting import plot_roc

table, curves = paper_experiment(n_frames=150, n_draws=10000, seed=1, npup=64)
c = curves["all"]
fig, ax = plt.subplots(figsize=(6, 4.5))
plot_roc({k: v for k, v in c.items() if "theory" not in k}, ax=ax,
         theory={k.split()[0]: v for k, v in c.items() if "theory" in k},
         title="paper scene, three channels")
fig.tight_layout()
print(table["channels", "test", "auc", "pd"])

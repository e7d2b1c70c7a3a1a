#!/usr/bin/env python3
"""Draws the sliding vectors of the chest-wall nodes that breast_sim_run writes (sliding.csv), seen
from the front onto the chest wall (x lateral/medial, z superior), after gravity and at the end of the
run, coloured by length (seed Figure 4 b, c).

usage: /usr/bin/python3 scripts/plot_sliding.py RUN_DIR/sliding.csv [OUT.png]
"""
import csv
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def main(path, out):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    if not rows:
        sys.exit(f"{path}: no chest-wall nodes")
    col = lambda k: np.array([float(r[k]) for r in rows])
    x, z = col("x_mm"), col("z_mm")
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2), constrained_layout=True)
    vmax = max(1e-9, max(np.hypot(col(f"{s}_dx_mm"), col(f"{s}_dz_mm")).max() for s in ("gravity", "final")))
    for ax, stage, title in zip(axes, ("gravity", "final"), ("after gravity (supine)", "after morphing to the supine target")):
        dx, dz = col(f"{stage}_dx_mm"), col(f"{stage}_dz_mm")
        length = np.sqrt(dx**2 + col(f"{stage}_dy_mm") ** 2 + dz**2)
        q = ax.quiver(x, z, dx, dz, length, angles="xy", scale_units="xy", scale=1.0, cmap="viridis", clim=(0, vmax),
                      width=0.003)
        ax.scatter(x, z, s=2, c="0.6")
        xs, zs = np.concatenate([x, x + dx]), np.concatenate([z, z + dz])
        ax.set_xlim(xs.min() - 5, xs.max() + 5)
        ax.set_ylim(zs.min() - 5, zs.max() + 5)
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm] (phantom: +x lateral)")
        ax.set_ylabel("z [mm] (superior)")
        ax.set_title(f"sliding on the chest wall {title}\nmax {length.max():.1f} mm, mean {length.mean():.1f} mm "
                     f"({len(rows)} wall nodes)")
    fig.colorbar(q, ax=axes, label="slide [mm] (arrows to scale)")
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "sliding_vectors.png")

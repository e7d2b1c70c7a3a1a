#!/usr/bin/python3
"""Quiver plot of the chest-wall sliding vectors from bench_sliding --csv (seed Figure 4 b, c).

usage: plot_sliding.py SLIDING.csv OUT.png [--title TEXT]
Projects onto the phantom's chest-wall plane coordinates (u = x lateral towards the patient's left,
v = z superior; LPS, mm). Colour: the limiting weight w of each node; arrows: its sliding vector,
drawn to scale (1 mm of slide = 1 mm on the plot) unless --scale is given.
"""
import csv
import sys

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt


def main():
    args = sys.argv[1:]
    if len(args) < 2:
        sys.exit(__doc__)
    title = "chest-wall sliding vectors"
    scale = 1.0
    if "--title" in args:
        title = args[args.index("--title") + 1]
    if "--scale" in args:
        scale = float(args[args.index("--scale") + 1])
    rows = list(csv.DictReader(open(args[0])))
    x = [float(r["x_mm"]) for r in rows]
    z = [float(r["z_mm"]) for r in rows]
    dx = [float(r["slide_x_mm"]) for r in rows]
    dz = [float(r["slide_z_mm"]) for r in rows]
    w = [float(r["weight"]) for r in rows]
    mag = [(a * a + float(r["slide_y_mm"]) ** 2 + b * b) ** 0.5 for a, b, r in zip(dx, dz, rows)]
    fig, ax = plt.subplots(figsize=(11, 4.6))
    sc = ax.scatter(x, z, c=w, s=6, cmap="viridis", vmin=0, vmax=1)
    ax.quiver(x, z, [scale * a for a in dx], [scale * b for b in dz], angles="xy", scale_units="xy", scale=1,
              width=0.0018, color="crimson")
    fig.colorbar(sc, ax=ax, label="limiting weight w (bimodal Gaussian)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm] (patient left +)")
    ax.set_ylabel("z [mm] (superior +)")
    ax.set_title("%s: max %.1f mm, arrows x%g" % (title, max(mag), scale))
    fig.tight_layout()
    fig.savefig(args[1], dpi=130)


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Speed-accuracy chart from bench_speed_accuracy's CSV (--csv FILE).

x = compute time to a settled state [s] (the settling steps; log scale), y = mean nodal displacement
error against the CalculiX reference [mm]; one curve per method, points labelled by element count;
the Pareto front over all points (no other point is both faster and more accurate) is highlighted.

usage: /usr/bin/python3 scripts/plot_speed_accuracy.py docs/speed_accuracy/speed_accuracy.csv
           [--out docs/speed_accuracy/speed_accuracy.png] [--y error_mean_mm] [--title TEXT]
       /usr/bin/python3 scripts/plot_speed_accuracy.py A.csv B.csv ... --out cases.png
           [--titles "case A,case B,..."]   (one panel per CSV, each with its own Pareto front)
Writes the PNG and, beside it, <stem>_pareto.csv (the front's points; with several CSVs a column
`case` names the panel).
"""
import argparse
import csv
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

LABELS = {
    "error_mean_mm": "mean nodal displacement error [mm]",
    "error_p95_mm": "95th-percentile nodal error [mm]",
    "error_max_mm": "largest nodal error [mm]",
    "lesion_error_max_mm": "largest lesion position error [mm]",
    "surface_distance_mean_mm": "mean surface distance [mm]",
}
STYLE = {
    "linear/multigrid": ("tab:gray", "s"),
    "corotated/multigrid": ("tab:blue", "o"),
    "corotated/cholmod": ("tab:cyan", "D"),
    "corotated+stiffening/multigrid": ("tab:red", "^"),
    "corotated+stiffening/cholmod": ("tab:orange", "v"),
    "corotated-det/multigrid": ("tab:green", "P"),
    "corotated-det/cholmod": ("tab:olive", "X"),
    "corotated-det+stiffening/multigrid": ("tab:purple", "*"),
    "corotated-det+stiffening/cholmod": ("tab:pink", "*"),
}
EXTRA_COLOURS = ["tab:brown", "tab:pink", "tab:purple", "black", "tab:olive", "tab:cyan"]


def style(method, extra):
    """Colour and marker of a method: the table above; "+sliding" and "uniform-E" variants take
    their base method's colour with another marker; anything else the next spare colour."""
    if method in STYLE:
        return STYLE[method]
    base = method.replace("+sliding", "").replace(" uniform-E", "")
    if base in STYLE:
        return STYLE[base][0], ("d" if "+sliding" in method else "x")
    if method not in extra:
        extra[method] = (EXTRA_COLOURS[len(extra) % len(EXTRA_COLOURS)], "o")
    return extra[method]


def pareto(points):
    """Points (t, e, row) not dominated by any other (faster-or-equal and more-accurate-or-equal)."""
    front = []
    best = float("inf")
    for t, e, r in sorted(points, key=lambda p: (p[0], p[1])):
        if e < best:
            front.append((t, e, r))
            best = e
    return front


def draw(ax, rows, y, title, extra):
    """One panel: a curve per method, points labelled by element count, the Pareto front."""
    methods = []
    for r in rows:
        if r["method"] not in methods:
            methods.append(r["method"])
    pts = []
    for m in methods:
        mr = sorted((r for r in rows if r["method"] == m), key=lambda r: int(r["elements"]))
        x = [float(r["settle_seconds"]) for r in mr]
        yv = [float(r[y]) for r in mr]
        color, marker = style(m, extra)
        ax.plot(x, yv, marker=marker, color=color, label=m, alpha=0.85)
        for r, xi, yi in zip(mr, x, yv):
            ok = r["settled"] == "1" and r["inverted"] == "0"
            lab = f"{int(r['elements']) / 1000:.0f}k" + ("" if ok else "!")
            ax.annotate(lab, (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7, color=color)
            pts.append((xi, yi, r))
    front = pareto(pts)
    ax.plot([p[0] for p in front], [p[1] for p in front], "-", color="black", lw=2.5, alpha=0.25, zorder=0,
            label="Pareto front")
    ax.scatter([p[0] for p in front], [p[1] for p in front], s=140, facecolors="none", edgecolors="black", zorder=5)
    ax.set_xscale("log")
    ax.set_xlabel("compute time to a settled state [s] (settling steps, log scale)")
    ax.set_ylabel(LABELS[y] + " (log scale)")
    ax.grid(True, which="both", alpha=0.3)
    # Log y too: a setting that fails (co-rotated with fixed E inverts elements, tens of mm off) would
    # otherwise squash the working ones (0.2-2 mm) onto the axis.
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend(fontsize=7)
    return front, pts


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv", nargs="+")
    ap.add_argument("--out", default=None)
    ap.add_argument("--y", default="error_mean_mm", choices=sorted(LABELS))
    ap.add_argument("--title", default=None)
    ap.add_argument("--titles", default=None, help="comma-separated panel titles (several CSVs)")
    a = ap.parse_args()
    out = a.out or os.path.join(os.path.dirname(a.csv[0]) or ".", "speed_accuracy.png")
    tables = []
    for path in a.csv:
        with open(path) as f:
            rows = list(csv.DictReader(f))
        if not rows:
            raise SystemExit(f"{path}: no rows")
        tables.append(rows)
    titles = a.titles.split(",") if a.titles else [os.path.splitext(os.path.basename(p))[0] for p in a.csv]
    if len(titles) != len(a.csv):
        raise SystemExit(f"--titles has {len(titles)} names for {len(a.csv)} CSV files")
    extra = {}
    if len(tables) == 1:
        fig, ax = plt.subplots(figsize=(9, 6))
        axes = [ax]
        titles = [a.title or "Speed against accuracy (reference: CalculiX neo-Hookean, NLGEOM)"]
    else:
        cols = 2
        nrows = (len(tables) + cols - 1) // cols
        fig, grid = plt.subplots(nrows, cols, figsize=(8 * cols, 5.5 * nrows), squeeze=False)
        axes = [grid[i // cols][i % cols] for i in range(len(tables))]
        for k in range(len(tables), nrows * cols):
            grid[k // cols][k % cols].axis("off")
        if a.title:
            fig.suptitle(a.title)
    fronts = []
    npts = 0
    for ax, rows, title in zip(axes, tables, titles):
        front, pts = draw(ax, rows, a.y, title, extra)
        fronts.append((title, front))
        npts += len(pts)
    fig.tight_layout()
    fig.savefig(out, dpi=130 if len(tables) == 1 else 110)
    pf = os.path.splitext(out)[0] + "_pareto.csv"
    with open(pf, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow((["case"] if len(tables) > 1 else []) + ["method", "elements", "settle_seconds", a.y])
        for title, front in fronts:
            for t, e, r in front:
                w.writerow(([title] if len(tables) > 1 else []) + [r["method"], r["elements"], t, e])
    print(f"wrote {out} and {pf} ({sum(len(fr) for _, fr in fronts)} Pareto points of {npts})")


if __name__ == "__main__":
    main()

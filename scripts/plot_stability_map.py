#!/usr/bin/python3
"""Heat maps of the stability map (breast_sim_stability_map --csv FILE).

usage: scripts/plot_stability_map.py [CSV] [OUT_DIR]
  CSV      default docs/stability_map/stability_map.csv
  OUT_DIR  default the CSV's folder

Writes
  stability_nu_dt.png     per method: Poisson ratio x time step, coloured by outcome, annotated with the
                          reason (inverted element count, reversal fraction, steps to settle, max |u|)
  stability_E_alpha.png   the one-factor axes: Young's modulus per method, initial alpha per method
"""
import csv
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

OUTCOMES = ["settled", "not_settled", "stalled", "inverted", "nan", "exploded"]
COLOURS = ["#4caf50", "#c5e1a5", "#ffb74d", "#e57373", "#9575cd", "#5d4037"]
LABELS = {"settled": "settled", "not_settled": "no inversion, still moving", "stalled": "stalled (reversal limit)",
          "inverted": "inverted elements", "nan": "NaN / solver failure", "exploded": "exploded (|u| > 1 m)"}
METHODS = ["linear", "corotated", "vonmises_no_reversal", "full", "explicit_euler", "anp", "anp_full"]
SHORT = {"linear": "linear FEM", "corotated": "co-rotated, fixed E", "vonmises_no_reversal": "von Mises, no reversal",
         "full": "full method", "explicit_euler": "explicit Euler", "anp": "ANP + barrier, fixed E",
         "anp_full": "ANP, full method"}
TITLES = {"linear": "linear FEM", "corotated": "co-rotated, fixed E", "vonmises_no_reversal": "von Mises, no reversal",
          "full": "full method (reversal + alpha control)", "explicit_euler": "explicit (symplectic) Euler",
          "anp": "ANP + barrier, fixed E", "anp_full": "ANP + barrier, full method"}


def load(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in ("youngs_modulus_pa", "poisson_ratio", "time_step_s", "alpha_scale", "reversal_fraction",
                  "max_displacement_mm", "final_alpha_per_pa", "volume_change_percent"):
            r[k] = float(r[k])
        for k in ("inverted_elements", "steps", "steps_to_settle", "reversed_steps"):
            r[k] = int(r[k])
    return rows


def note(r):
    o = r["outcome"]
    if o == "inverted":
        return "%d inv" % r["inverted_elements"]
    if o == "exploded":
        return "expl.\nstep %d" % r["steps"]
    if o == "nan":
        return "NaN"
    if o == "stalled":
        return "stalled"
    text = ("%d st" % r["steps_to_settle"]) if o == "settled" else "%d st,\nmoving" % r["steps"]
    if r["method"] == "full":
        text += "\n%.0f%% rev" % (100 * r["reversal_fraction"])
    return text + "\n%.0f mm" % r["max_displacement_mm"]


def heat(ax, cells, xs, ys, xlabel, ylabel, xfmt, yfmt, title):
    cmap = ListedColormap(COLOURS)
    grid = [[float("nan")] * len(xs) for _ in ys]
    for (x, y), r in cells.items():
        grid[ys.index(y)][xs.index(x)] = OUTCOMES.index(r["outcome"])
    ax.imshow(grid, cmap=cmap, vmin=-0.5, vmax=len(OUTCOMES) - 0.5, aspect="auto", origin="lower")
    for (x, y), r in cells.items():
        dark = r["outcome"] in ("nan", "exploded")
        ax.text(xs.index(x), ys.index(y), note(r), ha="center", va="center", fontsize=6,
                color="white" if dark else "black")
    ax.set_xticks(range(len(xs)))
    ax.set_xticklabels([xfmt(x) for x in xs], fontsize=7)
    ax.set_yticks(range(len(ys)))
    ax.set_yticklabels([yfmt(y) for y in ys], fontsize=7)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=8.5)


def legend(fig):
    fig.legend(handles=[Patch(color=c, label=LABELS[o]) for o, c in zip(OUTCOMES, COLOURS)], loc="lower center",
               ncol=6, fontsize=7, frameon=False)


def main():
    src = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "docs", "stability_map",
                                                              "stability_map.csv")
    out = sys.argv[2] if len(sys.argv) > 2 else os.path.dirname(os.path.abspath(src))
    rows = load(src)
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]

    nu_dt = [r for r in rows if r["axis"] == "nu_dt"]
    if nu_dt:
        E = nu_dt[0]["youngs_modulus_pa"]
        fig, axes = plt.subplots(1, len(methods), figsize=(3.1 * len(methods), 4.6), squeeze=False)
        for ax, m in zip(axes[0], methods):
            rs = [r for r in nu_dt if r["method"] == m]
            cells = {(r["time_step_s"], r["poisson_ratio"]): r for r in rs}
            xs = sorted({r["time_step_s"] for r in rs})
            ys = sorted({r["poisson_ratio"] for r in rs})
            heat(ax, cells, xs, ys, "dt [s]", "Poisson ratio", lambda v: "%g" % v, lambda v: "%g" % v, TITLES[m])
        fig.suptitle("Phantom, prone rest shape under supine gravity, E = %g kPa, initial alpha 1x: outcome per run "
                     "(st = steps to settle, rev = reversed steps, mm = max |u|)" % (E / 1000), fontsize=9)
        legend(fig)
        fig.tight_layout(rect=(0, 0.07, 1, 0.95))
        fig.savefig(os.path.join(out, "stability_nu_dt.png"), dpi=90)
        plt.close(fig)

    e_rows = [r for r in rows if r["axis"] == "E"]
    a_rows = [r for r in rows if r["axis"] == "alpha"]
    if e_rows or a_rows:
        # The E axis includes the nu_dt grid's point at nu 0.48, dt 0.033 s.
        base = [r for r in nu_dt if r["poisson_ratio"] == 0.48 and r["time_step_s"] == 0.033]
        fig, axes = plt.subplots(1, 2, figsize=(12.5, 3.8), gridspec_kw={"width_ratios": [3, 2]})
        rs = e_rows + base
        Es = sorted({r["youngs_modulus_pa"] for r in rs})
        ms = [m for m in methods if any(r["method"] == m for r in rs)]
        cells = {(r["youngs_modulus_pa"], ms.index(r["method"])): r for r in rs if r["method"] in ms}
        heat(axes[0], cells, Es, list(range(len(ms))), "E [kPa] (0.89, 1.48, 2.07 = shear modulus 0.3, 0.5, 0.7 kPa)",
             "", lambda v: "%.2f" % (v / 1000), lambda i: SHORT[ms[i]], "Young's modulus at nu 0.48, dt 0.033 s")
        alpha_methods = ("vonmises_no_reversal", "full", "anp_full")
        ra = a_rows + [r for r in nu_dt if r["method"] in alpha_methods and r["poisson_ratio"] == 0.48
                       and r["time_step_s"] in (0.033, 0.33)]
        keys = sorted({(r["time_step_s"], r["alpha_scale"]) for r in ra})
        ms2 = [m for m in alpha_methods if any(r["method"] == m for r in ra)]
        cells = {(keys.index((r["time_step_s"], r["alpha_scale"])), ms2.index(r["method"])): r for r in ra}
        heat(axes[1], cells, list(range(len(keys))), list(range(len(ms2))), "dt [s] / initial alpha (x default)", "",
             lambda i: "%g / %gx" % keys[i], lambda i: SHORT[ms2[i]],
             "Initial alpha at nu 0.48, E %g kPa" % (ra[0]["youngs_modulus_pa"] / 1000) if ra else "")
        legend(fig)
        fig.tight_layout(rect=(0, 0.08, 1, 1))
        fig.savefig(os.path.join(out, "stability_E_alpha.png"), dpi=90)
        plt.close(fig)
    print("wrote", ", ".join(f for f in ("stability_nu_dt.png", "stability_E_alpha.png")
                             if os.path.exists(os.path.join(out, f))), "in", out)


if __name__ == "__main__":
    main()

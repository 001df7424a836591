"""Markdown report of the paper reproduction: all tables, paper vs ours."""

from __future__ import annotations

DEFAULT_SIGMA = 0.005  # the model problem's noise (paper.Settings.sigma): see _noise_note


def _sci(v) -> str:
    """Three significant digits as the paper prints them: 1.82e-2, 1.98."""
    if v is None:
        return "–"
    if abs(v) >= 0.1:
        return f"{v:.2f}"
    m, e = f"{v:.2e}".split("e")
    return f"{m}e{int(e)}"


def _num(v, digits=1) -> str:
    return "–" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))


def markdown_table(header: list[str], rows: list[list[str]], left: tuple[str, ...] = ()) -> list[str]:
    """Lines of a Markdown table; columns are right-aligned except those named in ``left``."""
    align = ["---" if h in left else "---:" for h in header]
    return ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"] + ["| " + " | ".join(r) + " |" for r in rows]


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return markdown_table(header, rows) + [""]


def _cell(r: dict | None, qty: str) -> tuple[str, str]:
    """(ours, paper) strings of one model cell; capped cells are marked ≥, unconverged ones †."""
    if r is None:
        return "n/a", "–"
    if qty == "gn":
        ours = str(r["gn_iterations"]) + ("" if r["converged"] or r["capped"] else "†")
        return ours, _num(r["paper_gn"])
    ours = _num(r["cg_mean"])
    if r["capped"]:
        ours = "≥" + ours + " (capped)"
    return ours, _num(r["paper_cg"])


def _bars_section(bars: list[dict]) -> list[str]:
    out = ["## Table tab:laplace_scalability — 1D bar chain (appendix), overlap 1", "",
           "CG (x₀ = 0, tolerance 1e-8) stopped on the *natural* preconditioned residual norm "
           "√(rᵀM⁻¹r) ≤ 1e-8·√(r₀ᵀM⁻¹r₀) (`pcg(..., norm=\"natural\")`); λmin/λmax are the Lanczos "
           "estimates of M⁻¹K from the CG coefficients. *CG ‖r‖* is the count with the default rule "
           "‖r‖ ≤ 1e-8‖b‖, shown for comparison.", ""]
    header = ["subdomains", "bars", "1-lvl CG", "paper", "CG ‖r‖", "λmin", "paper", "λmax", "paper",
              "GDSW CG", "paper", "CG ‖r‖", "λmin", "paper", "λmax", "paper"]
    rows = []
    for r in bars:
        row = [str(r["subdomains"]), str(r["bars"])]
        for key in ("one_level", "gdsw"):
            e, p = r[key], r[key].get("paper", {})
            row += [str(e["cg"]), _num(p.get("cg")), str(e["cg_residual_norm"]),
                    _sci(e["lambda_min"]), _sci(p.get("lambda_min")), _sci(e["lambda_max"]), _sci(p.get("lambda_max"))]
        rows.append(row)
    out += _table(header, rows)
    mism = []
    for r in bars:
        for key in ("one_level", "gdsw"):
            e, p = r[key], r[key].get("paper")
            if not p:
                continue
            for q in ("lambda_min", "lambda_max"):
                if f"{e[q]:.2e}" != f"{p[q]:.2e}":
                    mism.append(f"{r['subdomains']} subdomains, {key.replace('_', '-')} "
                                f"{'λmin' if q == 'lambda_min' else 'λmax'}: ours {e[q]:.6g}, paper {_sci(p[q])}")
    cg_ok = all(r[k]["cg"] == r[k]["paper"]["cg"] for r in bars for k in ("one_level", "gdsw") if "paper" in r[k])
    out.append(f"CG counts: {'all equal to the paper' if cg_ok else 'see the deviations below'}. "
               "Eigenvalues that differ from the paper in the printed 3 digits:")
    out.append("")
    out += [f"- {m}" for m in mism] or ["- none"]
    out.append("")
    if mism:
        out += ["These Lanczos estimates have converged: they no longer change in the last CG steps, and λmin "
                "equals the smallest eigenvalue of the dense M⁻¹K (checked up to 32 subdomains). Ours lie just "
                "past a rounding boundary (1.99521 vs 1.995, 1.21451e-3 vs 1.215e-3). None of the variants tried "
                "moved them without breaking other entries: "
                "stopping on ‖r‖, ‖M⁻¹r‖ or the natural norm, x₀ = 0, dead reckoning or random, Dirichlet rows "
                "kept or eliminated, and several edge- and node-based placements of the Dirichlet bars and subdomain cuts.", ""]
    return out


def _lookup(model: list[dict]):
    return {(r["loops"], r["points_per_side"], r["preconditioner"], r["overlap"]): r for r in model}


def _perf_rows(model, keys, pcs):
    idx = _lookup(model)
    rows = []
    for L, P in keys:
        row = [str(L), str(P)]
        for pc in pcs:
            r = idx.get((L, P, pc, 1))
            gn, pgn = _cell(r, "gn")
            cg, pcg = _cell(r, "cg")
            row += [gn, pgn, cg, pcg]
        if any(idx.get((L, P, pc, 1)) for pc in pcs):
            rows.append(row)
    return rows


def _header(pcs, names):
    h = ["loops", "pts/side"]
    for pc in pcs:
        h += [f"{names[pc]} GN", "paper", f"{names[pc]} CG", "paper"]
    return h


NAMES = {"none": "None", "one-level": "One-level", "gdsw": "GDSW", "gdsw-norot": "GDSW w/o rot."}


def _noise_note(s: dict, model: list[dict]) -> str:
    gn = [r["gn_iterations"] for r in model if r["converged"]]
    steps = f"{min(gn)}–{max(gn)}" if gn else "–"
    if s["sigma"] != DEFAULT_SIGMA:
        return f"- Noise: σ = {s['sigma']:g}, seed {s['seed']} (set on the command line); GN steps: {steps}."
    return ("- Noise: the paper states neither σ nor the seed. `SchwarzOptimizer` ends the run when a "
            "Gauss–Newton step increases the error (as GTSAM's optimizers do), while the paper's plain GN "
            "keeps going; from dead reckoning the first full step increases the error once the trajectory is "
            "long enough (measured separately with seed 0: σ = 0.05 fails from 128 loops on, σ = 0.01 at "
            "1024 loops, σ = 0.0075 still converges at 1024 loops). "
            f"σ = {DEFAULT_SIGMA:g} converges at every size run here with a margin; the price is {steps} GN "
            "steps instead of the paper's 5–16 (listed as deviations below).")


def render(results: dict, figures: dict[str, str]) -> str:
    """The whole report as Markdown."""
    s, model, bars = results["settings"], results["model"], results["bars1d"]
    out = ["# Reproduction of *Overlapping Schwarz Preconditioners for Pose-Graph SLAM in Robotics*", "",
           f"Generated by `{results['command']}` in {results['seconds']:.0f} s"
           f"{' (quick subset)' if s['quick'] else ''}. Every number below is recomputed by that command; "
           "the paper's value stands next to ours.", "",
           "## Setup", "",
           f"- Model problem: `square_loops(loops, points_per_side, sigma={s['sigma']:g}, seed={s['seed']})` — "
           "odometry weight 20·I, loop-closure weight 100·I, prior on pose 0.",
           "- Solver: plain Gauss–Newton (`SchwarzOptimizer`, `method=\"gn\"`), one subdomain per loop "
           "(`partition=\"segments\"`), overlap 1 unless stated, unit (algebraic) coarse modes as in the paper.",
           f"- Stopping: the paper's only — ‖g‖ ≤ {s['gradient_tol']:g} or ‖g‖ ≤ {s['relative_gradient_tol']:g}·‖g₀‖ "
           f"(GTSAM's error-decrease rules off), at most {s['max_gn']} GN steps; CG relative residual "
           f"‖r‖ ≤ {s['cg_tol']:g}·‖b‖.",
           f"- Budget per case: {s['case_seconds']:g} s wall clock and {s['cg_cap']} CG iterations per solve; "
           "a case that hits either is marked *capped* (its average is then a lower bound).",
           _noise_note(s, model),
           "- *GN* is the number of Gauss–Newton steps (linear solves), *CG* the average CG iterations per "
           "GN step. † marks a run that stopped without meeting the gradient rule.", ""]
    out += _bars_section(bars)

    perf_keys = sorted({(r["loops"], r["points_per_side"]) for r in model
                        if "tab:numerical_performance" in r["tables"]})
    out += ["## Table tab:numerical_performance — loops × points per side", ""]
    out += _table(_header(("none", "one-level", "gdsw"), NAMES), _perf_rows(model, perf_keys, ("none", "one-level", "gdsw")))

    weak_keys = sorted({(r["loops"], 16) for r in model if r["points_per_side"] == 16 and r["overlap"] == 1})
    out += ["## Table tab:weak_numerical — weak scaling at 16 points per side (rows past 128 loops: beyond the paper)", ""]
    out += _table(_header(("none", "one-level", "gdsw"), NAMES), _perf_rows(model, weak_keys, ("none", "one-level", "gdsw")))

    out += ["## Table tab:weak_null — GDSW without and with the rotational coarse mode", ""]
    out += _table(_header(("gdsw-norot", "gdsw"), NAMES), _perf_rows(model, weak_keys, ("gdsw-norot", "gdsw")))

    out += _beyond_section(model)
    out += ["## Figures", ""]
    captions = {
        "scalability": "Fig. scalability — CG iterations per GN step vs loops (16 points per side); "
                       "dashed: the paper's values; right: overlap 1, 2, 3.",
        "hat": "Fig. hat — GDSW coarse basis functions of the interface poses (world-frame components, "
               "linearized at the ground truth) against the piecewise-linear hat functions.",
        "sparsity": "Fig. sparsity — sparsity pattern of H, 8 loops × 8 points per side; loop-closure "
                    "blocks in red, overlapping subdomains shaded.",
        "optimized_results": "Fig. optimized_results — optimized trajectory vs odometry (dead reckoning) vs "
                             "ground truth, 8 loops × 8 points per side.",
    }
    for key, name in figures.items():
        out += [f"**{captions.get(key, key)}**", "", f"![{key}]({name})", ""]
    if results.get("figure_notes"):
        out += [f"- {n}" for n in results["figure_notes"]] + [""]
    out += _deviation_section(results["deviations"])
    return "\n".join(out).rstrip() + "\n"


def _beyond_section(model):
    idx = _lookup(model)
    loops = sorted({r["loops"] for r in model if r["points_per_side"] == 16})
    out = ["## Beyond the paper — weak scaling to 1024 loops with overlap 1, 2 and 3 (16 points per side)", "",
           "Average CG iterations per GN step (GN steps in parentheses).", ""]
    header = ["loops", "poses"] + [f"{NAMES[pc]} δ={ov}" for pc in ("one-level", "gdsw") for ov in (1, 2, 3)]
    rows = []
    for L in loops:
        row = [str(L), str(4 * 16 * L + 1)]
        for pc in ("one-level", "gdsw"):
            for ov in (1, 2, 3):
                r = idx.get((L, 16, pc, ov))
                if r is None:
                    row.append("n/a")
                else:
                    cg, _ = _cell(r, "cg")
                    row.append(f"{cg} ({r['gn_iterations']})")
        rows.append(row)
    out += _table(header, rows)
    slow = [r for r in model if r["capped"]]
    if slow:
        out += ["Capped cases:", ""] + [f"- {r['loops']} loops × {r['points_per_side']}, {r['preconditioner']}, "
                                       f"overlap {r['overlap']}: {r['stop_reason']}" for r in slow] + [""]
    return out


def _deviation_section(devs):
    out = ["## Cells deviating more than 20 % from the paper", ""]
    if not devs:
        return out + ["None.", ""]
    reasons = list(dict.fromkeys(d["reason"] for d in devs))
    out += [f"{len(devs)} cells, grouped by reason.", ""]
    for reason in reasons:
        group = [d for d in devs if d["reason"] == reason]
        out += [f"**Reason:** {reason}", ""]
        rows = []
        for d in group:
            rel = f"{100 * d['relative']:+.0f} %" if "relative" in d else "–"
            ours = _num(d["ours"]) if isinstance(d["ours"], float) else str(d["ours"])
            rows.append([d["case"], d["quantity"], ours, _num(d["paper"]), rel, d["table"]])
        out += _table(["case", "quantity", "ours", "paper", "deviation", "table"], rows)
    return out

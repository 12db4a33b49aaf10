"""ArrayTac display tools: ``teletouch display characterize [--json] [--quick]``.

``characterize`` measures the simulated ArrayTac (firmware + plant) the way the paper measured
the hardware: step response (10-90 % rise and fall, overshoot, steady-state error), open- and
closed-loop bandwidth (min of -3 dB and -90 deg; transfer function cross-checked by a sine
sweep), and force-displacement curves for k in {0.5, 0.625, 0.75, 0.875, 1}.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``display`` subcommands."""
    sub = parser.add_subparsers(dest="display_command", metavar="ACTION", required=True)
    char = sub.add_parser("characterize", help="measure step, bandwidth and stiffness curves "
                          "of the simulated display")
    char.add_argument("--json", action="store_true", help="print one JSON object")
    char.add_argument("--quick", action="store_true", help="fewer sweep/force points")
    char.add_argument("--integrator", default="zoh", choices=["zoh", "rk4", "euler"],
                      help="plant integrator (default: zoh, exact)")


def _report_text(result: dict) -> str:
    from shared.report import format_table

    paper = result["paper"]
    rows = [{"figure": name, "simulator": result[name], "paper": paper[name]}
            for name in ("open_loop_bandwidth_hz", "closed_loop_bandwidth_hz", "rise_time_s",
                         "fall_time_s", "overshoot_pct", "steady_state_error_mm")]
    fr = result["frequency_response"]
    rows.append({"figure": "sweep open/closed bandwidth (Hz)",
                 "simulator": f"{fr['sweep_open_loop_bandwidth_hz']:.2f} / "
                              f"{fr['sweep_closed_loop_bandwidth_hz']:.2f}", "paper": "-"})
    stiff = [{"k": c["k"], "yield force (N)": c["yield_force_n"],
              "region B slope (N/mm)": c["region_b_stiffness_n_per_mm"],
              "secant at max force (N/mm)": c["secant_stiffness_n_per_mm"]}
             for c in result["force_displacement"]]
    step = result["step"]
    return "\n".join([
        f"ArrayTac simulator characterisation (step {step['step_low_mm']} -> "
        f"{step['step_high_mm']} mm, k = 1)", "", format_table(rows), "",
        "Force-displacement (pin at 3 mm):", "", format_table(stiff)])


def run(args: argparse.Namespace) -> int:
    """Run the chosen display action."""
    from local_site.arraytac_sim.characterize import characterize
    from shared.report import emit, emit_json

    result = characterize(quick=args.quick, integrator=args.integrator).to_dict()
    if args.json:
        emit_json(result)
    else:
        emit(_report_text(result))
    return 0

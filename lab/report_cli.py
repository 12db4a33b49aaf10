"""Write a self-contained HTML report of a session recording.

  teletouch report local.mcap                                  # -> local.html
  teletouch report local.mcap --remote remote.mcap --truth ground_truth.json -o report.html

Relief and stiffness maps with the findings, trajectory coverage, the findings against the
ground truth (when --truth is given; the demo writes one), the latency ledger as plots and
the pins commanded against measured. Images are embedded; the file opens anywhere.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the report arguments."""
    parser.add_argument("file", metavar="FILE.mcap", help="the local station's recording")
    parser.add_argument("-o", "--output", metavar="PATH.html",
                        help="where to write (default: FILE with .html)")
    parser.add_argument("--truth", metavar="JSON", help="the phantom's ground truth")
    parser.add_argument("--remote", metavar="FILE.mcap",
                        help="the remote station's recording of the same session")


def run(args: argparse.Namespace) -> int:
    """Write the report and print its path."""
    from pathlib import Path

    from lab.html_report import write_report
    from shared.report import emit

    out = Path(args.output) if args.output else Path(args.file).with_suffix(".html")
    emit(str(write_report(args.file, out, truth_path=args.truth, remote_path=args.remote)))
    return 0

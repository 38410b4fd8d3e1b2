"""The figure options shared by the commands that write figures (`--figure-format`, and
`--no-figures` where the figures are optional)."""

from __future__ import annotations

FIGURE_FORMATS = ("png", "svg", "pdf")  # png for a quick look; svg/pdf are vector (papers)


def add_figure_format(parser, *, optional: bool = False) -> None:
    """Add ``--figure-format png|svg|pdf`` (stored as ``args.figure_format``); with
    `optional`, also ``--no-figures`` (``args.figure_format`` None), exclusive with it."""
    group = parser.add_mutually_exclusive_group() if optional else parser
    group.add_argument(
        "--figure-format",
        choices=FIGURE_FORMATS,
        default="png",
        help="file format of the figures: png (default, 200 dpi), svg or pdf (vector)",
    )
    if optional:
        # drawing is a third of a fit's time or more where the runs are many (the
        # micro-robot folder: 5 of 17 s): skipped when only the numbers are wanted
        group.add_argument(
            "--no-figures",
            dest="figure_format",
            action="store_const",
            const=None,
            default="png",
            help="draw no figures (no figures/ folder; everything else is written as usual)",
        )

"""The figure options shared by the commands that write figures (`--figure-format`)."""

from __future__ import annotations

FIGURE_FORMATS = ("png", "svg", "pdf")  # png for a quick look; svg/pdf are vector (papers)


def add_figure_format(parser) -> None:
    """Add ``--figure-format png|svg|pdf`` (stored as ``args.figure_format``)."""
    parser.add_argument(
        "--figure-format",
        choices=FIGURE_FORMATS,
        default="png",
        help="file format of the figures: png (default, 200 dpi), svg or pdf (vector)",
    )

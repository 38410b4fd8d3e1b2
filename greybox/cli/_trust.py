"""``--trust-device PATH``: the consent a command needs to run device code a params.json names
from outside its own folder (the rule is `greybox._usercode.trusted_devices`)."""

from __future__ import annotations

TRUST_HELP = (
    "allow the device code at PATH (a .py file or a folder) named by the params.json; "
    "without it only a device file inside the params.json's folder, a built-in device or an "
    "installed package is imported (repeatable)"
)


def add_trust_device_option(parser) -> None:
    parser.add_argument(
        "--trust-device", action="append", default=[], metavar="PATH", help=TRUST_HELP
    )

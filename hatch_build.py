"""Build hook: the built-in devices and the demo data travel inside a regular wheel only.

A regular wheel packs the repository's models/ folder as `greybox/_builtin_models` (so it
installs no top-level `models` package) and the embedded data set as `greybox/_embedded`. An
editable install must not: there greybox finds both in the repository, and copies beside
the import hook would make a half `greybox` namespace folder in site-packages.
"""

from hatchling.builders.hooks.plugin.interface import BuildHookInterface

PACKED = {
    "models": "greybox/_builtin_models",
    "experiments/chevron_laser": "greybox/_embedded/chevron_laser",
}


class CustomBuildHook(BuildHookInterface):
    def initialize(self, version, build_data):
        if version == "standard":
            build_data["force_include"].update(PACKED)

"""The package surface: functions and their modules are both reachable under distinct names."""

from __future__ import annotations

import importlib
import subprocess
import sys

import morphgs


def test_render_and_curate_functions_do_not_hide_their_modules() -> None:
    rendering = importlib.import_module("morphgs.rendering")
    curation = importlib.import_module("morphgs.curation")
    assert morphgs.render is rendering.render and callable(morphgs.render)
    assert morphgs.curate is curation.curate and callable(morphgs.curate)
    # the modules are attributes of the package too, next to the functions
    assert morphgs.rendering is rendering and morphgs.curation is curation
    assert morphgs.curation.load_manifest is curation.manifest.load


def test_import_morphgs_does_not_import_torch() -> None:
    code = ("import sys, morphgs, morphgs.curation, morphgs.cli, morphgs.exports, morphgs.commands.export; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"

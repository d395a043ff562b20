"""Paths the file system refuses: a name over 255 bytes and a loop of symbolic links gave a traceback
(``OSError: [Errno 36] File name too long`` from ``Path.exists``, pathlib's ``RuntimeError: Symlink loop``) in
every command; one error line now names the path and what to do."""

from __future__ import annotations

import pytest

from _cli_helpers import one_error_line, run_cli


@pytest.mark.parametrize("command", [
    lambda p, png: ["info", p / ("a" * 300 + ".h5")],
    lambda p, png: ["simulate", p / ("a" * 300 + ".png"), "--out", p / "x.h5", "--duration", "0.1"],
    lambda p, png: ["simulate", png, "--out", p / ("a" * 300 + ".h5"), "--duration", "0.1"],
    lambda p, png: ["presets", "evk3-hd", "--plot", p / ("a" * 300 + ".png")],
], ids=["info-input", "simulate-input", "simulate-output", "presets-plot"])
def test_a_file_name_too_long_for_the_file_system_is_one_error_line(tmp_path, capsys, command):
    import numpy as np
    from PIL import Image

    png = tmp_path / "scene.png"
    Image.fromarray(np.full((8, 8), 128, np.uint8)).save(png)
    code, _, err = run_cli(capsys, *command(tmp_path, png))
    one_error_line(code, err, "the file name is too long for the file system (at most 255 bytes per name)")
    assert ("a" * 300) in err


def test_an_output_that_is_a_loop_of_symbolic_links_is_one_error_line(tmp_path, capsys):
    import numpy as np
    from PIL import Image

    png = tmp_path / "scene.png"
    Image.fromarray(np.full((8, 8), 128, np.uint8)).save(png)
    (tmp_path / "a.h5").symlink_to(tmp_path / "b.h5")
    (tmp_path / "b.h5").symlink_to(tmp_path / "a.h5")
    code, _, err = run_cli(capsys, "simulate", png, "--out", tmp_path / "a.h5", "--duration", "0.1")
    one_error_line(code, err, f"{tmp_path / 'a.h5'}: a loop of symbolic links")

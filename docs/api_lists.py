"""Write the API reference pages from the packages' own ``__all__`` (called by conf.py at build time).

A name in ``__all__`` that no group below lists still gets documented, under "Other", so the
reference cannot silently miss a public name; a listed name that left ``__all__`` is dropped.
The pages are build outputs (docs/.gitignore).
"""

from __future__ import annotations

import importlib
from pathlib import Path

TOP_GROUPS = [
    ("Parameters and presets", "Noise-model parameters (validated, units in the field names) and the shipped "
     "camera presets.", ["NoiseParams", "load_preset", "list_presets"]),
    ("Closed-form model and rates", "The exact per-trial probability, the paper's Gaussian form, expected rates "
     "with dead time, threshold mismatch and background.",
     ["event_probability", "log_event_probability", "expected_rate", "draw_thresholds", "background_rate",
      "draw_background"]),
    ("Simulation", "Noise events and counts of still scenes and videos, in memory or streamed.",
     ["sample_counts", "simulate_events", "iter_events", "simulate_video", "iter_video", "NoiseStream"]),
    ("Event arrays", "evnoise's event dtype ``(t µs, x, y, p)`` and conversions to the ``N x 4`` arrays "
     "of other tools.", ["count_events", "merge_events", "events_to_array", "events_from_array"]),
    ("Event files", "events.h5 and every camera-file format evnoise reads and writes "
     "(see :doc:`../formats`).", ["write_events", "read_events", "iter_event_chunks", "open_events",
                                  "EventWriter"]),
    ("Images and radiometry", "Image files to illuminance in lux.", ["image_to_lux", "read_image"]),
    ("Signal/noise separation and motion", "Telling scene events from noise events, and the static "
     "background behind motion.", ["Separator", "separate_events", "density_filter", "activity_filter",
                                   "iter_motion", "reconstruct_video"]),
    ("Errors", "Every error evnoise raises on bad input is one of these (the CLI prints one "
     "``evnoise: error:`` line and exits 2).", ["EvnoiseError", "InputError", "OutputError", "ParameterError"]),
]
#: names documented by hand on the page (data, not callables)
TOP_DATA = {
    "__version__": "The installed version of evnoise (a string, e.g. ``\"{v}\"``).",
    "EVENT_DTYPE": "The structured dtype of evnoise's event arrays: ``t`` int64 (microseconds), ``x`` "
                   "uint16, ``y`` uint16, ``p`` uint8 (1 = ON, 0 = OFF); arrays are sorted by ``t``.",
}

SUBPACKAGES = [
    ("calibration", "evnoise.calibration", "Calibration",
     "Fitting the model to measurements: rate or count tables per illuminance, flat-field recordings, "
     "and quiet (still-scene) recordings. Guide: :doc:`../guides/calibrate`.",
     [("Quiet recordings", ["quiet_window", "QuietWindow", "fit_quiet", "compare_to_recording",
                            "check_verdict", "failed_checks", "preset_toml"]),
      ("Rate tables and flat fields", ["Measurements", "read_measurements", "read_rate_table", "rate_table",
                                       "count_table", "flat_field", "read_flat_fields", "MonitorTable",
                                       "read_monitor_table", "grey_to_lux", "calibrate", "CalibrationResult",
                                       "plot_fit", "population_rate", "threshold_distribution", "nb_shape",
                                       "FIT_NAMES", "GOODNESS_P", "write_text_atomic"])]),
    ("generators", "evnoise.generators", "Dataset generators",
     "NE2I-style count/image pair datasets: sources, configuration, sharded and resumable generation. "
     "Guide: :doc:`../guides/datasets`.",
     [("Making a dataset", ["PairConfig", "make_dataset", "plan_dataset", "DatasetResult", "summarise_dataset"]),
      ("Reading a dataset", ["load_manifest", "PairDataset"]),
      ("Scene sources", ["FolderSource", "FilesSource", "PackagePhotos", "DeadLeaves", "DeadLeavesModel",
                         "dead_leaves", "linear_to_srgb"])]),
    ("reconstruct", "evnoise.reconstruct", "Reconstruction (PyTorch)",
     "The U-Net that turns noise-event counts into images, its training configuration, baselines and "
     "metrics. Needs ``pip install 'evnoise[train]'``. Guide: :doc:`../guides/reconstruct`.",
     [("Models and inference", ["Reconstructor", "load_model", "DEFAULT_MODEL", "default_model_path", "UNet",
                                "UNetConfig", "InputSpec", "read_checkpoint", "describe_checkpoint",
                                "checkpoint_summary", "reconstruct_video"]),
      ("Training data", ["TrainConfig", "NpzPairs", "PairList", "ResampledPairs", "open_pairs", "save_pairs_npz",
                         "split_by_source", "counts_from_h5", "bin_counts", "choose_window"]),
      ("Baselines and metrics", ["MLInversion", "count_image", "psnr", "ssim", "LPIPS", "lpips_distance",
                                 "install_weights", "format_table"]),
      ("Images", ["lux_to_display", "srgb_encode", "srgb_decode", "write_png"])]),
]

PLUGINS = [
    ("evnoise.plugins.tonic", "tonic transform", ["PhotonNoise"]),
    ("evnoise.plugins.v2e", "v2e EventEmulator wrapper (v2e itself is not needed to import it)",
     ["PhotonNoise", "noisy_emulators", "noisy_emulator_class", "grey_to_lux", "main"]),
    ("evnoise.plugins.frames", "any frame-driven emulator with v2e's interface",
     ["EmulatorNoise", "noise_rows", "merge_rows", "merge_with_positions", "interleave"]),
]


def _public(module) -> list[str]:
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n in dir(module) if not n.startswith("_")]
    return list(names)


def _autosummary(prefix: str, names: list[str]) -> list[str]:
    lines = ["", f".. currentmodule:: {prefix}", "", ".. autosummary::", "   :toctree: generated", "   :nosignatures:", ""]
    lines += [f"   {n}" for n in names]
    return lines + [""]


def _heading(text: str, char: str) -> list[str]:
    return [text, char * len(text), ""]


def _top_page(out: Path) -> None:
    import evnoise

    public = _public(evnoise)
    lines = [".. This page is written by docs/api_lists.py from evnoise.__all__ at build time.", ""]
    lines += _heading("evnoise", "=")
    lines += [".. module:: evnoise", "",
              "The package's public names (``evnoise.__all__``). Importing evnoise is cheap: the "
              "numerical parts load on first use. Every random function takes ``rng`` (a "
              ":class:`numpy.random.Generator`, an int seed, or ``None``); each pixel has its own random "
              "stream, so a seed gives the same events whatever the number of threads.", ""]
    seen = set()
    for title, text, names in TOP_GROUPS:
        names = [n for n in names if n in public]
        if not names:
            continue
        seen.update(names)
        lines += _heading(title, "-") + [text] + _autosummary("evnoise", names)
    data = [n for n in public if n in TOP_DATA]
    if data:
        lines += _heading("Constants", "-")
        for n in data:
            seen.add(n)
            lines += [f".. data:: {n}", "", "   " + TOP_DATA[n].format(v=evnoise.__version__), ""]
    other = [n for n in public if n not in seen]
    if other:
        lines += _heading("Other", "-") + ["Public names not yet filed under a group above."]
        lines += _autosummary("evnoise", other)
    (out / "evnoise.rst").write_text("\n".join(lines) + "\n", encoding="utf-8")


def _sub_page(out: Path, stem: str, modname: str, title: str, text: str, groups) -> None:
    module = importlib.import_module(modname)
    public = _public(module)
    lines = [f".. This page is written by docs/api_lists.py from {modname}.__all__ at build time.", ""]
    lines += _heading(f"{modname}: {title}", "=") + [f".. module:: {modname}", "", text, ""]
    seen = set()
    for gtitle, names in groups:
        names = [n for n in names if n in public]
        if names:
            seen.update(names)
            lines += _heading(gtitle, "-") + _autosummary(modname, names)
    other = [n for n in public if n not in seen]
    if other:
        lines += _heading("Other", "-") + _autosummary(modname, other)
    (out / f"{stem}.rst").write_text("\n".join(lines) + "\n", encoding="utf-8")


def _plugins_page(out: Path) -> None:
    lines = [".. This page is written by docs/api_lists.py at build time.", ""]
    lines += _heading("evnoise.plugins: tonic and v2e", "=") + [
        ".. module:: evnoise.plugins", "",
        "Photon noise where people already add noise to events. Neither tonic nor v2e is imported by "
        "evnoise: the plugins follow their data conventions. Guide: :doc:`../guides/plugins`.", ""]
    for modname, text, names in PLUGINS:
        module = importlib.import_module(modname)
        public = _public(module)
        names = [n for n in names if n in public] + [n for n in public if n not in names]
        lines += _heading(modname, "-") + [f".. module:: {modname}", "", f"The {text}."]
        lines += _autosummary(modname, names)
    (out / "plugins.rst").write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_lists(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    _top_page(out)
    for stem, modname, title, text, groups in SUBPACKAGES:
        _sub_page(out, stem, modname, title, text, groups)
    _plugins_page(out)

"""``make_dataset``: plan the shards, run them (in-process, a process pool or Dask), resume, write the manifest.

Output folder::

    DIR/manifest.json              written last, atomically: its presence means "complete"
    DIR/shards/<split>-<k>.h5      one HDF5 file per shard (see :mod:`.shards`)
    DIR/.evnoise-progress/         while running: plan.json, one record per finished shard,
                                   a lock file; removed when the manifest is written

(:mod:`.folder` holds these names and prepares, locks and reads back the folder.)

Determinism. The plan (which source goes to which split and shard) depends only on the
options and the list of item ids; every pair depends only on the seed and its identity
(:mod:`.pairs`); a shard's bytes depend only on its pairs. So any number of workers, a Dask
cluster, or an interrupted run resumed later all give the same files, and the manifest,
which holds no timestamps, is the same too.

Resume. Running the same job again on the same folder keeps every shard whose record (size
and SHA-256) matches the file, regenerates the others, and finishes the manifest. A
complete dataset is verified the same way (a corrupt or missing shard is regenerated). A
folder holding a dataset made with different options is refused (pass ``overwrite=True``).

Killed runs. Each shard is recorded the moment its file is complete, by whoever made it
(:func:`make_and_record_shard`, the same in-process, in a pool worker or on Dask), so a run
killed by any signal, SIGKILL included, loses at most the shards being written. Pool workers
end with the process that started them. A killed writer leaves its temporary file
(``.<name>.<pid>-<hex>.tmp``); the next run into the folder removes those whose process is gone.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import secrets
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from evnoise._pool import collect_results
from evnoise._version import __version__
from evnoise.errors import InputError, OutputError, ParameterError

from .config import COMPRESSIONS, COUNT_MAX, LEVELS, MODES, PairConfig
from .folder import (
    MANIFEST,
    PREVIEW,  # noqa: F401 - importable from here as before the split
    PROGRESS_DIR,
    SHARDS_DIR,
    FolderLock,
    dataset_member,
    discard_empty,
    prepare_folder,
    read_json,
    remove_stale_temporaries,
    shard_verified,
    stored_seed,
    write_json,
)
from .shards import FORMAT, FORMAT_VERSION, file_sha256

__all__ = ["make_dataset", "plan_dataset", "DatasetResult", "Plan", "ShardTask", "SPLITS", "MANIFEST",
           "resolve_sources"]

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
_SPLIT_SALT = "evnoise-split-v1:"


# --------------------------------------------------------------------------------------
# planning
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ShardTask:
    """One shard: its name, split and items ``((source_index, item_id), ...)``."""

    name: str
    split: str
    items: tuple

    @property
    def file(self) -> str:
        return f"{SHARDS_DIR}/{self.name}.h5"


@dataclass(frozen=True)
class Plan:
    """Everything decided before any pair is made (a pure function of options and item ids)."""

    config: PairConfig  # with the seed resolved
    sources: tuple
    shards: tuple  # of ShardTask, in split order then index
    split_sources: dict  # split -> number of sources planned
    fingerprint: str

    @property
    def n_samples(self) -> int:
        return sum(len(t.items) for t in self.shards) * self.config.samples_per_source

    def record(self) -> dict:
        """What identifies the job (stored in the progress folder and the manifest)."""
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "evnoise_version": __version__,
                "fingerprint": self.fingerprint, "config": self.config.to_dict(),
                "sources": [s.spec() for s in self.sources]}


def existing_records(root: Path, plan: Plan) -> dict:
    """Records of shards finished earlier (from the manifest or the progress folder), unverified."""
    records = {}
    manifest = read_json(root / MANIFEST) if (root / MANIFEST).exists() else None
    progress = root / PROGRESS_DIR
    plan_file = read_json(progress / "plan.json") if (progress / "plan.json").exists() else None
    for state in (manifest, plan_file):
        if state is None:
            continue
        if not isinstance(state, dict) or state.get("fingerprint") != plan.fingerprint:
            raise OutputError(_mismatch(root, state, plan))
    if manifest is not None:
        for entry in manifest.get("shards", []):
            records[entry["name"]] = {**entry, "skipped": [s for s in manifest.get("skipped", [])
                                                          if s.get("shard") == entry["name"]]}
    if progress.is_dir():
        for p in sorted(progress.glob("*.done.json")):
            rec = read_json(p)
            if isinstance(rec, dict) and "name" in rec:
                records[rec["name"]] = rec
    return records


def _mismatch(root: Path, state, plan: Plan) -> str:
    what = "a different dataset"
    if isinstance(state, dict) and isinstance(state.get("config"), dict):
        new = plan.config.to_dict()
        diff = sorted(k for k in set(new) | set(state["config"]) if new.get(k) != state["config"].get(k))
        if state.get("evnoise_version") != __version__:
            diff.append(f"evnoise version {state.get('evnoise_version')} -> {__version__}")
        if state.get("sources") != [s.spec() for s in plan.sources]:
            diff.append("sources")
        if diff:
            what = f"a dataset made with different options (differs in: {', '.join(diff)})"
        else:
            what = "a dataset of a different list of source images"
    return (f"output folder {root} already holds {what}; pass overwrite=True to replace it, "
            "or choose another folder")


def resolve_sources(sources) -> tuple:
    """Source objects from a source, a path (folder or image file) or a list of them.

    Folders become :class:`~.sources.FolderSource`; image files, together, one
    :class:`~.sources.FilesSource`.
    """
    from .sources import DeadLeaves, FilesSource, FolderSource, PackagePhotos

    if sources is None:
        raise InputError("no scene source: give image folders or files, package photos or a procedural source")
    if isinstance(sources, (str, os.PathLike)) or hasattr(sources, "items") and hasattr(sources, "load"):
        sources = [sources]
    out, files = [], []
    for s in sources:
        if isinstance(s, (FolderSource, FilesSource, PackagePhotos, DeadLeaves)) or (
                hasattr(s, "items") and hasattr(s, "load") and hasattr(s, "spec")):
            out.append(s)
            continue
        if not isinstance(s, (str, os.PathLike)):
            raise InputError(f"not a scene source: {s!r}")
        path = Path(s)
        if path.is_dir():
            out.append(FolderSource(os.fspath(path)))
        elif path.is_file():
            files.append(os.fspath(path))
        else:
            raise InputError(f"image folder or file not found: {path}")
    if files:
        out.append(FilesSource(tuple(files)))
    if not out:
        raise InputError("no scene source: give image folders or files, package photos or a procedural source")
    return tuple(out)


def _split_key(item_id: str) -> str:
    return hashlib.sha256((_SPLIT_SALT + item_id).encode("utf-8")).hexdigest()


def _assign_splits(ids: list, fractions) -> dict:
    """``id -> split``: sources ranked by a hash of their id; the first ``round(f n)`` go to
    test, the next to val, the rest to train (at least one source in every split whose
    fraction is > 0, when there are enough sources)."""
    n = len(ids)
    f_train, f_val, f_test = fractions
    n_test = round(f_test * n)
    n_val = round(f_val * n)
    positive = [f > 0 for f in (f_train, f_val, f_test)]
    if n >= sum(positive):
        if f_test > 0:
            n_test = max(n_test, 1)
        if f_val > 0:
            n_val = max(n_val, 1)
        if f_train > 0:
            while n - n_test - n_val < 1:
                if n_val > 1 or (n_val == 1 and f_val == 0):
                    n_val -= 1
                elif n_test > 1 or (n_test == 1 and f_test == 0):
                    n_test -= 1
                else:
                    break
    n_test = min(n_test, n)
    n_val = min(n_val, n - n_test)
    ranked = sorted(ids, key=_split_key)
    out = {}
    for k, item in enumerate(ranked):
        out[item] = "test" if k < n_test else "val" if k < n_test + n_val else "train"
    return out


def plan_dataset(sources, config: PairConfig) -> Plan:
    """The split and shard plan of a job (``config.seed`` must be set).

    Lists the sources' items without loading any image; nothing is written.

    Parameters
    ----------
    sources : source, path, or list of them
        Scene sources, as in :func:`make_dataset`; item ids must be unique across them.
    config : PairConfig
        Dataset options, with ``seed`` set.

    Returns
    -------
    Plan
        The configuration, the sources, the shards of each split with their items, the number of sources
        per split, and the job's fingerprint.
    """
    if config.seed is None:
        raise ParameterError("plan_dataset needs a config with a seed")
    sources = resolve_sources(sources)
    items, owner = [], {}
    for k, source in enumerate(sources):
        for item_id in source.items():
            if item_id in owner:
                raise InputError(f"two scene sources both have an item {item_id!r}; ids must be unique "
                                 "(rename one of the files)")
            owner[item_id] = k
            items.append((k, item_id))
    if not items:
        raise InputError("the scene sources hold no images")
    split_of = _assign_splits([i for _, i in items], config.splits)
    per_shard = max(1, config.shard_size // config.samples_per_source)
    shards, counts = [], {}
    for split in SPLITS:
        members = [it for it in items if split_of[it[1]] == split]
        counts[split] = len(members)
        for j, lo in enumerate(range(0, len(members), per_shard)):
            shards.append(ShardTask(f"{split}-{j:05d}", split, tuple(members[lo:lo + per_shard])))
    body = {"format_version": FORMAT_VERSION, "evnoise_version": __version__, "config": config.to_dict(),
            "sources": [s.spec() for s in sources],
            "shards": [[t.name, [i for _, i in t.items]] for t in shards]}
    fingerprint = hashlib.sha256(json.dumps(body, sort_keys=True).encode("utf-8")).hexdigest()
    return Plan(config, sources, tuple(shards), counts, fingerprint)


# --------------------------------------------------------------------------------------
# one shard (runs in a worker process, a Dask worker, or in-process)
# --------------------------------------------------------------------------------------
_SAMPLERS: dict = {}
_SAMPLERS_LOCK = threading.Lock()


def _sampler(config: PairConfig, threads: int):
    from .pairs import CountSampler

    key = (json.dumps(config.to_dict(), sort_keys=True), threads)
    with _SAMPLERS_LOCK:
        sampler = _SAMPLERS.get(key)
        if sampler is None:
            if len(_SAMPLERS) > 8:
                _SAMPLERS.clear()
            sampler = _SAMPLERS[key] = CountSampler(config, threads)
    return sampler


@dataclass(frozen=True)
class _Job:
    root: str
    config: PairConfig
    sources: tuple
    task: ShardTask
    threads: int


def generate_shard(job: _Job, on_sample=None) -> dict:
    """Make one shard file; returns its record (size, checksum, sources written, skipped ones)."""
    from evnoise.radiometry import fit_to_sensor

    from .pairs import crop_levels, display_image, draw_crop, sample_seed, to_uint16
    from .shards import ShardWriter
    from .sources import LoadContext

    config, task = job.config, job.task
    sampler = _sampler(config, job.threads)
    ctx = LoadContext(config.sensor_shape, config.encoding, config.clip_invalid, config.seed)
    path = Path(job.root) / task.file
    white = config.display_white_lux
    attrs = {"evnoise_version": __version__, "split": task.split, "shard": task.name, "binning": config.binning,
             "counts_order": "ON,OFF", "image_encoding": "srgb", "white_lux": white,
             "params": config.noise_params.to_dict(), "seed": int(config.seed)}
    timings = {"scene": 0.0, "illuminance": 0.0, "sampling": 0.0, "write": 0.0}
    written, skipped, saturated = [], [], 0
    clock = time.perf_counter
    with ShardWriter(path, config.pair_shape, config.compression, attrs) as writer:
        for k, item_id in task.items:
            t0 = clock()
            try:
                y, kind = job.sources[k].load(item_id, ctx)
                y = fit_to_sensor(y, config.sensor_shape, config.fit)
            except InputError as exc:
                skipped.append({"source": item_id, "split": task.split, "shard": task.name, "reason": str(exc)})
                continue  # its pairs are taken off the progress bar's total when the shard is done
            timings["scene"] += clock() - t0
            written.append(item_id)
            for c in range(config.crops_per_image):
                t0 = clock()
                draw = draw_crop(config, config.seed, item_id, c, kind)
                codes, sums = crop_levels(y, draw, config.lux_step, config.binning)
                image = display_image(sums, config.binning, config.lux_step, white)
                timings["illuminance"] += clock() - t0
                t0 = clock()
                image_index = writer.add_image(image)
                timings["write"] += clock() - t0
                for window_s, window_us in zip(config.windows_s, config.windows_us, strict=True):
                    t0 = clock()
                    seed = sample_seed(config.seed, item_id, c, window_us)
                    counts, n_sat = to_uint16(sampler.sample(codes, window_us, seed))
                    t1 = clock()
                    writer.append(counts, draw.box, source=item_id, crop_index=c, window_s=window_s,
                                  window_us=window_us, lux_scale=white, max_lux=draw.scale_lux,
                                  contrast_gamma=draw.gamma, seed=seed, saturated=n_sat, image_index=image_index)
                    timings["sampling"] += t1 - t0
                    timings["write"] += clock() - t1
                    saturated += n_sat
                    if on_sample is not None:
                        on_sample(1)
        t0 = clock()
        writer.close()
        n = writer.n
        timings["write"] += clock() - t0
    t0 = clock()
    digest = file_sha256(path)
    timings["checksum"] = clock() - t0
    return {"name": task.name, "file": task.file, "split": task.split, "samples": n, "sources": written,
            "bytes": path.stat().st_size, "sha256": digest, "saturated_bins": saturated, "skipped": skipped,
            "timings": timings}


def record_file(root, name: str) -> Path:
    """The progress record of shard ``name`` (written as soon as its file is complete)."""
    return Path(root) / PROGRESS_DIR / f"{name}.done.json"


def make_and_record_shard(job: _Job, on_sample=None) -> dict:
    """The resume protocol, the same in every executor (in-process, a process pool, Dask): make the
    shard (written under a temporary name, renamed when complete), then at once write its record
    (name, size, SHA-256) into the progress folder. A run killed at any moment keeps every shard
    whose record was written, and a re-run keeps exactly those whose file still matches it."""
    rec = generate_shard(job, on_sample)
    write_json(record_file(job.root, rec["name"]), {k: v for k, v in rec.items() if k != "timings"},
               what="progress record")
    return rec


def _run_job(job: _Job) -> dict:
    return make_and_record_shard(job)


# --------------------------------------------------------------------------------------
# the job
# --------------------------------------------------------------------------------------
@dataclass
class DatasetResult:
    """What :func:`make_dataset` did."""

    path: Path
    manifest: dict
    generated: list = field(default_factory=list)  # shard names made by this run
    reused: list = field(default_factory=list)  # shard names kept (verified by checksum)
    skipped: list = field(default_factory=list)  # skipped sources with reasons
    seconds: float = 0.0
    timings: dict = field(default_factory=dict)  # seconds per phase, summed over generated shards
    workers: int = 1
    sampler: str = ""

    @property
    def n_samples(self) -> int:
        return int(self.manifest["totals"]["samples"])


def _default_threads(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def make_dataset(sources, out_dir, config: PairConfig | None = None, *, workers: int | None = None,
                 scheduler=None, threads: int | None = None, progress: bool = False,
                 overwrite: bool = False) -> DatasetResult:
    """Generate (or resume, or verify) a dataset of count/image pairs.

    Parameters
    ----------
    sources : source, path, or list of them
        Scene sources: :class:`~.sources.FolderSource`, :class:`~.sources.FilesSource`,
        :class:`~.sources.PackagePhotos`, :class:`~.sources.DeadLeaves`, or folders / image
        files by path.
    out_dir : str or os.PathLike
        Output folder (created; must be new, empty, or hold this same job to resume it).
    config : PairConfig, optional
        Dataset options (default :class:`PairConfig()`). With ``seed=None`` the seed of an
        interrupted run in ``out_dir`` is reused, else a fresh one is drawn (and stored).
    workers : int, optional
        Local worker processes (default: the CPU count, at most the number of shards to make);
        1 runs in this process. Never changes the output. Workers are spawned: a script that
        uses them needs the usual ``if __name__ == "__main__":`` guard.
    scheduler : str or distributed.Client, optional
        Run the shards on a Dask distributed cluster (address like ``tcp://host:8786``, or a
        client). Workers must see ``out_dir`` and the source files at the same paths (a shared
        file system). Needs ``pip install 'evnoise[dask]'``. Never changes the output.
    threads : int, optional
        Threads per worker for the event simulator and the general count sampler (default: the
        CPU count divided by ``workers``; 1 on Dask). Never changes the output.
    progress : bool
        Show a progress bar (tqdm) of pairs made.
    overwrite : bool
        Replace a dataset of different options in ``out_dir``.

    Returns
    -------
    DatasetResult
        The dataset's folder and manifest, the shards made and reused, the sources skipped, and timings.

    Raises
    ------
    InputError
        No sources, an empty folder, duplicate item ids.
    OutputError
        ``out_dir`` unwritable, not empty, locked by another run, or holding another dataset.
    ParameterError
        Invalid options.
    """
    started = time.perf_counter()
    config = PairConfig() if config is None else config
    if not isinstance(config, PairConfig):
        raise ParameterError(f"config must be a PairConfig, got {type(config).__name__}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ParameterError(f"workers must be an integer >= 1, got {workers!r}")
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ParameterError(f"threads must be an integer >= 1, got {threads!r}")
    root = Path(out_dir)
    sources = resolve_sources(sources)
    if config.params is None:  # resolve the preset once: every worker uses these exact parameters
        config = config.replace(params=config.noise_params)
    if config.seed is None:
        stored = None if overwrite or not root.is_dir() else stored_seed(root)
        seed = stored if stored is not None else secrets.randbelow(1 << 32)
        if stored is None:
            log.info("no seed given; using seed %d (stored in the manifest)", seed)
        config = config.replace(seed=seed)
    plan = plan_dataset(sources, config)  # lists the sources: fails before anything is written
    created = not root.exists()
    prepare_folder(root, overwrite)
    progress_dir = root / PROGRESS_DIR
    progress_dir.mkdir(exist_ok=True)
    with FolderLock(progress_dir / "lock"):
        for path in remove_stale_temporaries(root):  # left by a killed run (we hold the lock)
            log.info("removed %s, left by an interrupted run", path)
        records = existing_records(root, plan)
        (root / SHARDS_DIR).mkdir(exist_ok=True)
        planned = {t.name: len(t.items) * config.samples_per_source for t in plan.shards}
        valid, reused = {}, []
        for task in plan.shards:
            rec = records.get(task.name)
            # a record's pair count is read below (progress, manifest totals): a whole number the shard can hold
            counted = rec is not None and type(rec.get("samples")) is int and 0 <= rec["samples"] <= planned[task.name]
            if counted and shard_verified(root, rec):
                valid[task.name] = rec
                reused.append(task.name)
            elif rec is not None:
                log.warning("shard %s is missing or does not match its checksum; making it again", task.file)
        todo = [t for t in plan.shards if t.name not in valid]
        if not todo and (root / MANIFEST).exists():
            shutil.rmtree(progress_dir, ignore_errors=True)
            manifest = read_json(root / MANIFEST)
            return DatasetResult(root, manifest, [], reused, list(manifest.get("skipped", [])),
                                 time.perf_counter() - started, {}, 0, manifest.get("sampler", ""))
        (root / MANIFEST).unlink(missing_ok=True)  # from here on the dataset is incomplete
        if reused:
            log.info("resuming: %d shard(s) verified and kept, %d to make", len(reused), len(todo))
        bar = None
        if progress:
            from tqdm.auto import tqdm

            # the pairs a skipped source would have made are neither done nor to do: the total drops by them
            done = sum(valid[t.name]["samples"] for t in plan.shards if t.name in valid)
            dropped = sum(planned[t.name] - valid[t.name]["samples"] for t in plan.shards if t.name in valid)
            bar = tqdm(total=plan.n_samples - dropped, initial=done, unit="pair", desc="make-dataset", smoothing=0.1)
        timings: dict = {}
        in_process = scheduler is None and (workers == 1 or (workers is None and len(todo) <= 1))

        def finished(rec: dict) -> None:
            for s in rec["skipped"]:
                log.warning("skipped %s: %s", s["source"], s["reason"])
            for key, value in rec.pop("timings", {}).items():
                timings[key] = timings.get(key, 0.0) + value
            valid[rec["name"]] = rec  # its record is on disk already (make_and_record_shard)
            if bar is not None:
                if not in_process:  # in process, the bar moved pair by pair
                    bar.update(rec["samples"])
                if rec["samples"] < planned[rec["name"]]:  # a source skipped: its pairs are not to come
                    bar.total -= planned[rec["name"]] - rec["samples"]
                    bar.refresh()

        try:
            # in the try: a failure to write these (a full disk) also leaves no empty dataset behind
            write_json(progress_dir / "plan.json", plan.record(), what="progress plan")
            for name, rec in valid.items():  # a manifest's records become progress records
                if not (progress_dir / f"{name}.done.json").exists():
                    write_json(progress_dir / f"{name}.done.json", rec, what="progress record")
            if not todo:  # every shard recorded by an interrupted run: only the manifest is missing
                n_workers = 0
            elif scheduler is not None:
                if workers is not None:
                    log.info("workers= is not used with a Dask scheduler")
                n_workers = _run_dask(root, plan, todo, scheduler, threads or 1, finished)
            elif in_process:
                n_workers = 1
                thr = threads or _default_threads(1)
                step = bar.update if bar is not None else None
                for task in todo:
                    finished(make_and_record_shard(_Job(os.fspath(root), plan.config, plan.sources, task, thr), step))
            else:
                n_workers = min(workers or (os.cpu_count() or 1), len(todo))
                _run_pool(root, plan, todo, n_workers, threads or _default_threads(n_workers), finished)
        except Exception:
            if not valid:  # nothing made: no empty dataset left (the folder goes too if this run created it)
                if bar is not None:
                    bar.close()
                    bar = None
                remove_stale_temporaries(root)
                discard_empty(root, created)
            raise
        finally:
            if bar is not None:
                bar.close()
        remove_stale_temporaries(root)  # a Dask worker lost while writing a shard left its temporary file
        manifest = _manifest(plan, valid)
        if manifest["totals"]["samples"] == 0 and manifest["skipped"]:
            discard_empty(root, created)
            first = manifest["skipped"][0]
            raise InputError(f"no pair could be made: all {len(manifest['skipped'])} source image(s) were "
                             f"skipped (first: {first['source']}: {first['reason']})")
        write_json(root / MANIFEST, manifest, what="manifest")
        shutil.rmtree(progress_dir, ignore_errors=True)
    from .pairs import CountSampler

    return DatasetResult(root, manifest, [t.name for t in todo], reused, manifest["skipped"],
                         time.perf_counter() - started, timings, n_workers,
                         CountSampler(plan.config).method)


def _start_method() -> str:
    """``"spawn"`` (clean workers, safe with threads), unless ``__main__`` names a file that a spawned
    worker cannot re-import (a script read from stdin, ``python -``): then ``"fork"`` where available.

    As with any spawn-based pool, a Python script that calls :func:`make_dataset` with workers
    must guard its top level with ``if __name__ == "__main__":``.
    """
    import multiprocessing
    import sys

    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    if main_file is not None and not os.path.isfile(main_file) and "fork" in multiprocessing.get_all_start_methods():
        return "fork"
    return "spawn"


#: how often (seconds) a pool worker checks that the process that started it is still alive
_PARENT_CHECK_S = 0.5


def _die_with_parent(parent_pid: int) -> None:
    """Pool worker initializer: end this worker when ``parent_pid`` (the process running
    ``make_dataset``) dies, even by SIGKILL, which gives it no chance to stop its pool. Without
    this the workers (and through them multiprocessing's resource tracker) ran on forever, holding
    the caller's standard output. On Linux the kernel sends SIGKILL at the parent's death
    (``prctl(PR_SET_PDEATHSIG)``); everywhere a daemon thread also checks ``os.getppid()``. The
    shard being written is left as a temporary file, which the next run into the folder removes.

    The worker also ignores SIGINT (Ctrl-C in a terminal reaches the whole process group): the
    process running ``make_dataset`` decides, and ends its workers itself (:func:`_stop_workers`).
    A KeyboardInterrupt raised inside a worker could land in the middle of the pool's own queue
    traffic (a half-read job, a half-sent result) and leave the pool blocked for ever."""
    import signal
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):  # pragma: no cover - no prctl: the thread below does it
            pass
    if os.getppid() != parent_pid:  # the parent died before the line above
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(_PARENT_CHECK_S)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="evnoise-parent-watch", daemon=True).start()


def _parent_logging() -> tuple:
    """What a pool worker needs to log as this process does: the root logger's level, the formatter of its first
    handler (None when there is none or it is not a plain :class:`logging.Formatter`, which a spawned worker might
    not be able to unpickle), and the once-per-process warnings already given here."""
    from evnoise._kernels._jit import warnings_given

    root = logging.getLogger()
    formatter = next((h.formatter for h in root.handlers if h.formatter is not None), None)
    return root.getEffectiveLevel(), formatter if type(formatter) is logging.Formatter else None, warnings_given()


def _start_worker(parent_pid: int, parent_logging: tuple) -> None:
    """Pool worker initializer: :func:`_die_with_parent`, and log as the parent does. A spawned worker starts with
    no logging set up, so its warnings came out bare (Python's last-resort handler) where the command's own lines
    read "evnoise: WARNING: ..."; and a once-per-process warning the parent had given (compiled kernels that cannot
    be cached) came again from each worker."""
    from evnoise._kernels._jit import note_warnings_given

    _die_with_parent(parent_pid)
    level, formatter, given = parent_logging
    root = logging.getLogger()
    if not root.handlers:  # spawned (a forked worker has the parent's handlers already)
        handler = logging.StreamHandler()
        if formatter is not None:
            handler.setFormatter(formatter)
        root.addHandler(handler)
        root.setLevel(level)
    note_warnings_given(given)


def _run_pool(root, plan, todo, n_workers, threads, finished) -> None:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    ctx = multiprocessing.get_context(_start_method())
    jobs = [_Job(os.fspath(root), plan.config, plan.sources, t, threads) for t in todo]
    pool = ProcessPoolExecutor(max_workers=n_workers, mp_context=ctx, initializer=_start_worker,
                               initargs=(os.getpid(), _parent_logging()))
    try:
        collect_results(pool, _run_job, jobs, finished)  # each shard as it is done (its record is on disk already)
    except KeyboardInterrupt:  # Ctrl-C, or the CLI's SIGTERM (evnoise.cli.Terminated)
        _stop_workers(pool, root)
        raise
    except BaseException:  # a shard failed: the shards under way finish and are recorded
        try:
            pool.shutdown(wait=True, cancel_futures=True)
        except KeyboardInterrupt:
            _stop_workers(pool, root)
        raise
    pool.shutdown(wait=True)


#: how long (seconds) an interrupted run waits for its terminated workers to end before killing them
_STOP_GRACE_S = 5.0


def _stop_workers(pool, root) -> None:
    """End an interrupted run's pool now: queued shards are cancelled, the workers are terminated
    (their shards are abandoned: a shard is only kept once recorded) and the temporary files they
    leave are removed. Waiting for them to finish their shards kept an interrupted run alive for the
    length of a shard, or for ever when a worker had been interrupted inside the pool's queues."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # CPython's pool keeps them here
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    deadline = time.monotonic() + _STOP_GRACE_S
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
    for process in processes:
        if process.is_alive():
            process.kill()
            process.join(1.0)
    remove_stale_temporaries(Path(root))


def _run_dask(root, plan, todo, scheduler, threads, finished) -> int:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ParameterError("scheduler= needs Dask: pip install 'evnoise[dask]'") from None
    own = not isinstance(scheduler, Client)
    try:
        client = Client(scheduler, set_as_default=False) if own else scheduler
    except (OSError, TimeoutError, ValueError) as exc:
        raise OutputError(f"cannot connect to the Dask scheduler {scheduler!r}: {exc}") from None
    try:
        futures = [client.submit(_run_job, _Job(os.fspath(root), plan.config, plan.sources, t, threads),
                                 key=f"evnoise-shard-{plan.fingerprint[:16]}-{t.name}", retries=1)
                   for t in todo]
        try:
            for fut in as_completed(futures, loop=client.loop):
                finished(fut.result())
        except BaseException:
            client.cancel(futures)
            raise
        n = len(client.scheduler_info().get("workers", {})) or 1
    finally:
        if own:
            client.close()
    return n


def _manifest(plan: Plan, records: dict) -> dict:
    config = plan.config
    shards, skipped = [], []
    splits = {s: {"sources_planned": plan.split_sources[s], "sources": 0, "samples": 0, "shards": 0}
              for s in SPLITS}
    saturated = 0
    for task in plan.shards:
        rec = records[task.name]
        shards.append({k: rec[k] for k in ("name", "file", "split", "samples", "sources", "bytes", "sha256",
                                             "saturated_bins")})
        skipped.extend(rec["skipped"])
        sp = splits[task.split]
        sp["sources"] += len(rec["sources"])
        sp["samples"] += rec["samples"]
        sp["shards"] += 1
        saturated += rec["saturated_bins"]
    h, w = config.pair_shape
    params = config.noise_params
    trials = max(config.windows_us) * 1e-6 * params.trial_rate_hz
    max_count = config.binning**2 * (math.floor(trials) + 1)
    from .pairs import CountSampler

    return {
        **plan.record(),
        "sampler": CountSampler(config).method,
        "pair": {
            "counts": {"shape": [2, h, w], "dtype": "uint16", "order": ["ON", "OFF"],
                       "binning": config.binning},
            "image": {"shape": [h, w], "dtype": "float32", "encoding": "srgb", "range": [0.0, 1.0],
                      "white_lux": config.display_white_lux},
            "lux_levels": LEVELS,
        },
        "overflow": {"max_possible_count": max_count, "count_max": COUNT_MAX,
                     "policy": "binned counts above 65535 saturate at 65535; the per-pair column 'saturated' "
                               "counts them"},
        "splits": splits,
        "shards": shards,
        "skipped": skipped,
        "totals": {"samples": sum(s["samples"] for s in splits.values()),
                   "sources": sum(s["sources"] for s in splits.values()),
                   "sources_planned": sum(plan.split_sources.values()),
                   "skipped_sources": len(skipped), "saturated_bins": saturated,
                   "bytes": sum(s["bytes"] for s in shards), "shards": len(shards)},
    }


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_positive(value) -> bool:
    """A finite number > 0 (not a bool, not a string)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def _shape_problem(value, name: str, optional: bool = False) -> str | None:
    if optional and value is None:
        return None
    if not (isinstance(value, list) and len(value) == 2 and all(_is_int(v) and v > 0 for v in value)):
        return f"its config field {name!r} is {str(value)[:60]!r}, not [height, width] in whole pixels > 0"
    return None


def _choice_problem(cfg: dict, key: str, choices) -> str | None:
    value = cfg.get(key)
    if key not in cfg or not ((value is None and None in choices) or (isinstance(value, str) and value in choices)):
        return f"its config field {key!r} is {str(value)[:60]!r}, not one of {', '.join(map(str, choices))}"
    return None


def _is_fraction(value) -> bool:
    """A finite number >= 0 (not a bool, not a string)."""
    return _is_positive(value) or (isinstance(value, (int, float)) and not isinstance(value, bool) and value == 0)


def _config_problem(cfg) -> str | None:
    """What in a manifest's ``config`` is not of the type and range its readers use (one field named), or None."""
    from evnoise.radiometry import FIT_MODES

    if not isinstance(cfg, dict):
        return "its 'config' entry is not a record"
    for key in ("crops_per_image", "binning", "shard_size"):
        value = cfg.get(key)
        if not (_is_int(value) and value >= 1):
            return f"its config field {key!r} is {str(value)[:60]!r}, not a whole number >= 1"
    if not (_is_int(cfg.get("seed")) and cfg["seed"] >= 0):
        return f"its config field 'seed' is {str(cfg.get('seed'))[:60]!r}, not a whole number >= 0"
    windows = cfg.get("windows_s")
    if not (isinstance(windows, list) and windows and all(_is_positive(w) for w in windows)):
        return f"its config field 'windows_s' is {str(windows)[:60]!r}, not a list of finite windows > 0 seconds"
    if not _is_positive(cfg.get("white_lux")):
        return f"its config field 'white_lux' is {str(cfg.get('white_lux'))[:60]!r}, not a finite number > 0 (lux)"
    for key in ("max_lux", "lux_scale", "contrast"):
        value = cfg.get(key)
        if not (isinstance(value, list) and len(value) == 2 and all(_is_positive(v) for v in value)):
            return f"its config field {key!r} is {str(value)[:60]!r}, not a range [low, high] of finite numbers > 0"
    splits = cfg.get("splits")
    if not (isinstance(splits, list) and len(splits) == 3 and all(_is_fraction(f) for f in splits)
            and sum(splits) > 0):
        return (f"its config field 'splits' is {str(splits)[:60]!r}, not three fractions >= 0 (train, val, test) "
                "with a positive sum")
    problem = (_shape_problem(cfg.get("sensor_shape"), "sensor_shape")
               or _shape_problem(cfg.get("crop_shape"), "crop_shape", optional=True)
               or _choice_problem(cfg, "fit", FIT_MODES) or _choice_problem(cfg, "mode", MODES)
               or _choice_problem(cfg, "compression", COMPRESSIONS))
    if problem:
        return problem
    if not (isinstance(cfg.get("preset"), str) and cfg["preset"]):
        return f"its config field 'preset' is {str(cfg.get('preset'))[:60]!r}, not a preset name"
    if not isinstance(cfg.get("params"), dict):
        return f"its config field 'params' is {str(cfg.get('params'))[:60]!r}, not a record of noise parameters"
    from evnoise.params import NoiseParams

    try:
        NoiseParams.from_dict(cfg["params"])
    except (ParameterError, TypeError, ValueError) as exc:
        return f"its config field 'params' does not hold valid noise parameters: {str(exc)[:200]}"
    return None


def _sources_problem(sources) -> str | None:
    """The ``sources`` entry: a list of source records, each with the field of its kind (as ``spec()`` writes it)."""
    fields = {"folder": ("path", str, "a path"), "files": ("paths", list, "a list of paths"),
              "dead-leaves": ("count", int, "a whole number"), "package-photos": ("packages", list, "a list of names")}
    if not (isinstance(sources, list) and all(isinstance(s, dict) for s in sources)):
        return "its 'sources' entry is not a list of source records"
    for spec in sources:
        if spec.get("kind") in fields:
            key, kind, what = fields[spec["kind"]]
            value = spec.get(key)
            if not isinstance(value, kind) or isinstance(value, bool) or (
                    kind is list and not all(isinstance(v, str) for v in value)):
                return (f"its 'sources' entry has a {spec['kind']} source whose {key!r} is {str(value)[:60]!r}, "
                        f"not {what}")
    return None


def _pair_problem(cfg: dict, pair) -> str | None:
    """The ``pair`` entry against the config: counts ``[2, h, w]`` and image ``[h, w]`` of the crop (or sensor)
    after binning, uint16 and float32, or what differs."""
    counts = pair.get("counts") if isinstance(pair, dict) else None
    image = pair.get("image") if isinstance(pair, dict) else None
    shape = counts.get("shape") if isinstance(counts, dict) else None
    if not (isinstance(shape, list) and len(shape) == 3 and all(_is_int(v) and v > 0 for v in shape)
            and _is_int(counts.get("binning")) and isinstance(image, dict)):
        return "its 'pair' entry does not give the counts' shape [2, h, w] and binning"
    b = cfg["binning"]
    h, w = cfg.get("crop_shape") or cfg["sensor_shape"]
    expected = [2, h // b, w // b]
    if shape != expected or counts["binning"] != b:
        return (f"its pair counts have shape {shape} (binning {counts['binning']}), but its config (a "
                f"{w}x{h} {'crop' if cfg.get('crop_shape') else 'sensor'}, binning {b}) gives {expected}")
    if image.get("shape") != expected[1:]:
        return f"its pair image has shape {str(image.get('shape'))[:60]}, not the counts' {expected[1:]}"
    if counts.get("dtype", "uint16") != "uint16" or image.get("dtype", "float32") != "float32":
        return (f"its pairs are {counts.get('dtype')!r} counts and {image.get('dtype')!r} images; this evnoise "
                "reads uint16 counts and float32 images")
    return None


def _manifest_problem(m: dict) -> str | None:
    """What in a manifest's entries is not of the kind its readers (``info``, :class:`PairDataset`) use, or None.

    The one place a manifest's fields are checked (types, finite, in range), each problem naming its field.
    """
    def ints(d, keys):
        return isinstance(d, dict) and all(_is_int(d.get(k)) and d.get(k) >= 0 for k in keys)

    cfg, totals, pair, splits = m.get("config"), m.get("totals"), m.get("pair"), m.get("splits")
    problem = _config_problem(cfg)
    if problem:
        return problem
    if not ints(totals, ("samples", "bytes", "shards", "saturated_bins")):
        return "its 'totals' entry is not a record of counts (samples, bytes, shards, saturated_bins)"
    problem = _pair_problem(cfg, pair)
    if problem:
        return problem
    if not (isinstance(splits, dict) and set(splits) <= set(SPLITS)
            and all(ints(v, ("samples", "sources", "sources_planned", "shards")) for v in splits.values())):
        return f"its 'splits' entry is not a record of {'/'.join(SPLITS)} counts"
    skipped = m.get("skipped", [])
    if not (isinstance(skipped, list) and all(isinstance(e, dict) and isinstance(e.get("source"), str)
                                              and isinstance(e.get("reason"), str) for e in skipped)):
        return "its 'skipped' entry is not a list of source/reason records"
    problem = _sources_problem(m.get("sources"))
    if problem:
        return problem
    for key in ("sampler", "evnoise_version"):
        if not isinstance(m.get(key, ""), str):
            return f"its {key!r} entry is {str(m.get(key))[:60]!r}, not a name"
    for entry in m["shards"]:
        if not (entry.get("split") in SPLITS and ints(entry, ("samples",)) and isinstance(entry.get("sources"), list)
                and isinstance(entry.get("file"), str)):
            return "a record of its 'shards' entry lacks split, samples, sources or file"
    return None


def load_manifest(path) -> tuple:
    """``(root, manifest)`` of a dataset folder (or its ``manifest.json``); InputError if incomplete.

    Parameters
    ----------
    path : str or os.PathLike
        The dataset's folder, or its ``manifest.json``.

    Returns
    -------
    root : pathlib.Path
        The dataset's folder.
    manifest : dict
        The manifest, checked (format, version, shard records; every file it names lies in ``root``).

    Raises
    ------
    InputError
        No dataset there, an incomplete one (an interrupted run), or a damaged or newer manifest.
    """
    path = Path(path)
    root = path.parent if path.name == MANIFEST and path.is_file() else path
    if not root.is_dir():
        raise InputError(f"dataset not found: {path}")
    manifest_path = root / MANIFEST
    if not manifest_path.is_file():
        if (root / PROGRESS_DIR).exists():
            raise InputError(f"dataset {root} is incomplete (an interrupted make-dataset run); run the same "
                             "command again to resume it")
        from itertools import islice

        from evnoise.radiometry import IMAGE_EXTENSIONS

        hint = ""
        if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in islice(root.iterdir(), 1000)):
            hint = "; a folder of images? make a dataset of it first (make-dataset)"
        raise InputError(f"{root} is not an evnoise dataset (no {MANIFEST}){hint}")
    data = read_json(manifest_path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"{manifest_path} is not an evnoise pairs manifest")
    version = data.get("format_version", 0)
    if not _is_int(version):
        raise InputError(f"{manifest_path} is damaged: its format_version is {str(version)[:40]!r}, not a number")
    if version > FORMAT_VERSION:
        raise InputError(f"{manifest_path} has format version {version}; this evnoise "
                         f"reads up to {FORMAT_VERSION} (upgrade evnoise)")
    shards = data.get("shards")
    if not isinstance(shards, list) or not all(isinstance(s, dict) for s in shards):
        raise InputError(f"{manifest_path} is damaged: its 'shards' entry is not a list of records")
    problem = _manifest_problem(data)
    if problem:
        raise InputError(f"{manifest_path} is damaged: {problem}")
    for entry in shards:  # every file a manifest names is read only from inside the dataset folder
        dataset_member(root, entry.get("file"))
    return root, data

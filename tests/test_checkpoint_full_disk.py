"""A checkpoint that cannot be written (a full disk): one OutputError line naming it, and no file left behind."""

from __future__ import annotations

import shutil
from collections import namedtuple

import pytest

import evnoise as ev

torch = pytest.importorskip("torch")

from evnoise.reconstruct.checkpoint import InputSpec, save_checkpoint  # noqa: E402
from evnoise.reconstruct.unet import UNet  # noqa: E402

#: what torch 2's zip writer raises when the disk fills during ``torch.save`` (no errno in it)
TORCH_FULL_DISK = "[enforce fail at inline_container.cc:672] . unexpected pos 123 vs 456"
_Usage = namedtuple("_Usage", "total used free")


def _save(path):
    net = UNet(base_channels=8, channel_mults=(1, 2), groups=4, stem=1)
    return save_checkpoint(path, model_config=net.config, input_spec=InputSpec(window_s=0.5),
                           state_dict=net.state_dict())


def _partial_then_fail(obj, f, *args, **kwargs):
    """Write part of the archive (as torch does before the disk fills), then fail as torch does."""
    with open(f, "wb") as fh:
        fh.write(b"PK\x03\x04" + bytes(1000))
    raise RuntimeError(TORCH_FULL_DISK)


def _checks(message: str, path) -> None:
    assert len(message.splitlines()) == 1, message
    assert message.startswith(f"cannot write checkpoint {path}: "), message
    assert "enforce fail" not in message and "inline_container" not in message, message


def test_a_full_disk_while_saving_a_checkpoint_says_so_and_leaves_no_file(tmp_path, monkeypatch):
    """torch's "enforce fail at inline_container.cc:672 ... unexpected pos" was the whole message: the folder's
    free space now tells that the disk is full."""
    monkeypatch.setattr(torch, "save", _partial_then_fail)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: _Usage(10**9, 10**9, 0))
    path = tmp_path / "m.pt"
    with pytest.raises(ev.OutputError) as info:
        _save(path)
    _checks(str(info.value), path)
    assert "the disk is full" in str(info.value) and str(tmp_path) in str(info.value), info.value
    assert list(tmp_path.iterdir()) == []  # neither the checkpoint nor its partial temporary file


def test_a_failed_checkpoint_save_with_room_left_gives_torch_words_without_their_cxx_prefix(tmp_path, monkeypatch):
    """Room left on the disk: not called full; torch's own words, minus "[enforce fail at inline_container.cc:...]"."""
    monkeypatch.setattr(torch, "save", _partial_then_fail)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: _Usage(10**12, 10**9, 10**11))
    path = tmp_path / "m.pt"
    with pytest.raises(ev.OutputError) as info:
        _save(path)
    _checks(str(info.value), path)
    assert "disk is full" not in str(info.value) and "unexpected pos 123 vs 456" in str(info.value), info.value
    assert list(tmp_path.iterdir()) == []

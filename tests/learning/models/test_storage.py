"""Loading model files: the messages of files that cannot be loaded here."""

from __future__ import annotations

import pytest
import torch

from diffcontact.learning.models.physical import LearnedModel
from diffcontact.learning.models.storage import load_model, load_torch_file, save_model

no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")


@no_cuda
@pytest.mark.parametrize("map_location", ["cuda", "cuda:0", torch.device("cuda")])
def test_a_good_file_loaded_onto_missing_cuda_says_so(tmp_path, map_location):
    """``load_model(run, map_location="cuda")`` without CUDA said the good file "cannot be
    read (truncated or corrupted?)"."""
    save_model(LearnedModel("CP3", hidden=(4,)), tmp_path / "model.pt")
    with pytest.raises(ValueError) as info:
        load_model(tmp_path, map_location=map_location)
    message = str(info.value)
    assert "corrupted" not in message
    assert f"map_location={map_location!r}" in message
    assert "CUDA is not available on this machine" in message
    assert "map_location='cpu'" in message
    assert "\n" not in message
    assert load_model(tmp_path, map_location="cpu").model_name == "CM-CD-CLNN"  # the file is good


@no_cuda
def test_load_torch_file_names_missing_cuda_for_any_file(tmp_path):
    path = tmp_path / "t.pt"
    torch.save({"w": torch.zeros(2)}, path)
    with pytest.raises(ValueError, match=r"^checkpoint .*t\.pt cannot be loaded with "
                       r"map_location='cuda': CUDA is not available"):  # fmt: skip
        load_torch_file(path, "checkpoint", map_location="cuda")
    assert torch.equal(load_torch_file(path, "checkpoint")["w"], torch.zeros(2))


def test_a_truncated_file_is_still_called_corrupted(tmp_path):
    path = save_model(LearnedModel("CP3", hidden=(4,)), tmp_path / "model.pt")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cannot be read \(truncated or corrupted\?\)"):
        load_model(path)

"""The shared checkpoint reader and strict layout check (models/checkpoints.py) that every learned model uses."""

from __future__ import annotations

import json

import pytest
import torch

from navcrafter.models import checkpoints


class ModelWeightsError(ValueError):
    pass


def test_listing_shortens_long_lists_and_says_how_many_more():
    assert checkpoints.listing(["a", "b"]) == "a, b"
    assert checkpoints.listing([f"k{i}" for i in range(13)], limit=3) == "k0, k1, k2 ... (+10 more)"


def test_layout_problems_name_missing_unexpected_and_mis_shaped_entries():
    expected = {"a": (2, 3), "b": (4,), "c": ()}
    assert checkpoints.layout_problems({"a": torch.zeros(2, 3), "b": [4], "c": torch.tensor(1.0)}, expected) == []
    problems = checkpoints.layout_problems({"a": torch.zeros(3, 2), "x": (1,)}, expected, optional=["c"])
    assert problems == ["missing keys [b]", "unexpected keys [x]", "shape mismatch [a: file [3, 2] vs model [2, 3]]"]
    with pytest.raises(ModelWeightsError, match=r"^f\.safetensors: the M layout: missing keys \[b, c\]\. Fix it$"):
        checkpoints.check_layout({"a": (2, 3)}, expected, ModelWeightsError, "f.safetensors: the M layout",
                                 hint=". Fix it")


def test_read_state_dict_reads_safetensors_and_tensor_only_files_and_refuses_pickled_code(tmp_path):
    from safetensors.torch import save_file

    sd = {"w": torch.arange(6.0).reshape(2, 3)}
    save_file(sd, str(tmp_path / "m.safetensors"))
    state, extra = checkpoints.read_state_dict(tmp_path / "m.safetensors", ModelWeightsError, "M")
    assert torch.equal(state["w"], sd["w"]) and extra == {}
    torch.save({"model": sd, "model_config": {"depth": 2}}, tmp_path / "official.pt")
    state, extra = checkpoints.read_state_dict(tmp_path / "official.pt", ModelWeightsError, "M")
    assert torch.equal(state["w"], sd["w"]) and extra == {"model_config": {"depth": 2}}
    torch.save({"model": torch.nn.Linear(2, 2)}, tmp_path / "pickled.pt")
    with pytest.raises(ModelWeightsError, match=r"pickled\.pt: not a tensor-only torch checkpoint.*weights_only"):
        checkpoints.read_state_dict(tmp_path / "pickled.pt", ModelWeightsError, "M")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ModelWeightsError, match=r"list\.pt: expected a M state dict"):
        checkpoints.read_state_dict(tmp_path / "list.pt", ModelWeightsError, "M")
    (tmp_path / "bad.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(ModelWeightsError, match="not a readable safetensors file"):
        checkpoints.read_state_dict(tmp_path / "bad.safetensors", ModelWeightsError, "M")
    with pytest.raises(ModelWeightsError, match="M checkpoint .*nope.pt does not exist"):
        checkpoints.read_state_dict(tmp_path / "nope.pt", ModelWeightsError, "M")


def test_safetensors_files_follow_the_index_and_refuse_pickles(tmp_path):
    from safetensors.torch import save_file

    (tmp_path / "pytorch_model.bin").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match=r"pytorch_model\.bin.*only safetensors are read"):
        checkpoints.safetensors_files(tmp_path)
    save_file({"a": torch.zeros(2)}, str(tmp_path / "diffusion_pytorch_model-00001-of-00002.safetensors"))
    save_file({"a": torch.zeros(3)}, str(tmp_path / "diffusion_pytorch_model-00002-of-00002.safetensors"))
    shards = [p.name for p in checkpoints.safetensors_files(tmp_path)]
    assert shards == ["diffusion_pytorch_model-00001-of-00002.safetensors",
                      "diffusion_pytorch_model-00002-of-00002.safetensors"]
    with pytest.raises(ModelWeightsError, match="key a also in"):
        checkpoints.safetensors_layout(checkpoints.safetensors_files(tmp_path), ModelWeightsError)
    (tmp_path / "diffusion_pytorch_model.safetensors.index.json").write_text(
        json.dumps({"weight_map": {"a": "diffusion_pytorch_model-00002-of-00002.safetensors"}}))
    files = checkpoints.safetensors_files(tmp_path)
    assert [p.name for p in files] == ["diffusion_pytorch_model-00002-of-00002.safetensors"]
    assert checkpoints.safetensors_layout(files, ModelWeightsError) == {"a": (3,)}

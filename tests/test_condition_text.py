"""A prompt's text condition (mld_core.condition.text): the conditioning tricks in their order (a bare command worded
as a sentence, the content anchor, then the side contrast against the mirrored wording, itself anchored), and the
cache that encodes each prompt once."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from mld_core.condition import side_contrast
from mld_core.condition.content_anchor import ContentAnchorConfig
from mld_core.condition.text import TextCache, encode
from mld_core.models.text_encoder import TextEmbedding


class _Encoder:
    """A stand-in text encoder: a text's vector counts its letters and its side words; token rows as many as words."""

    def __init__(self):
        self.calls = []

    def __call__(self, texts):
        self.calls.append(list(texts))
        pooled = F.normalize(torch.tensor([[len(t), t.count("left"), t.count("right"), 1.0] for t in texts]), dim=-1)
        words = max(len(t.split()) for t in texts)
        mask = torch.tensor([[i < len(t.split()) for i in range(words)] for t in texts])
        return TextEmbedding(pooled, pooled[:, None, :].repeat(1, words, 1) * mask[..., None], mask)


class _Anchor:
    """A stand-in content anchor: every vector moved by ``strength`` towards the last axis."""

    dim = 4

    def anchored(self, pooled, plain, strength):
        return F.normalize(pooled + strength * torch.tensor([0.0, 0.0, 0.0, 1.0]), dim=-1)


def _config(anchor_weight: float, contrast: float, commands_as_sentences: bool = True):
    return SimpleNamespace(content_anchor=ContentAnchorConfig(weight=anchor_weight), side_contrast=contrast,
                           commands_as_sentences=commands_as_sentences)


def test_the_anchor_comes_first_and_the_contrast_pushes_from_the_anchored_mirror():
    encoder, anchor = _Encoder(), _Anchor()
    prompts = ["a person turns left", "a person walks"]
    emb = encode(prompts, encoder, _config(0.5, 0.5), anchor)
    own = anchor.anchored(encoder(prompts).pooled, None, 0.5)  # (2, D)
    mirrored = anchor.anchored(encoder(["a person turns right"]).pooled, None, 0.5)  # (1, D)
    assert torch.allclose(emb.pooled[0], side_contrast.contrasted(own[:1], mirrored, 0.5)[0], atol=1e-6)
    assert torch.allclose(emb.pooled[1], own[1], atol=1e-6)  # no side named: anchored only
    assert torch.equal(emb.tokens, encoder(prompts).tokens)  # the tricks move the sentence vector only
    plain = encode(prompts, encoder, _config(0.0, 0.0), anchor)
    assert torch.equal(plain.pooled, encoder(prompts).pooled)  # both off: the encoder's own vectors
    assert not torch.allclose(encode(prompts, encoder, _config(0.0, 0.5), anchor).pooled[0], emb.pooled[0])


def test_a_bare_command_is_encoded_as_the_captions_word_it_and_its_mirror_too():
    encoder = _Encoder()
    prompts = ["turn left", "a man walks"]
    emb = encode(prompts, encoder, _config(0.0, 0.5), None)
    assert encoder.calls[0] == ["a person turns left", "a man walks"]  # a description is left as it is
    assert encoder.calls[1] == ["a person turns right"]  # the side contrast's mirror of the worded command
    own = encoder(["a person turns left"]).pooled
    assert torch.allclose(emb.pooled[0], side_contrast.contrasted(own, encoder(["a person turns right"]).pooled,
                                                                  0.5)[0], atol=1e-6)
    encoder.calls.clear()
    encode(prompts, encoder, _config(0.0, 0.0, commands_as_sentences=False), None)
    assert encoder.calls == [["turn left", "a man walks"]]  # switched off: as typed


def test_commands_are_worded_with_a_subject_and_a_third_person_verb():
    from mld_core.condition.wording import as_sentence, third_person

    cases = {"jump": "a person jumps", "Jump!": "a person jumps!", "squat down": "a person squats down",
             "do a cartwheel": "a person does a cartwheel", "please wave your left hand": "a person waves their left hand",
             "walking backwards": "a person is walking backwards", "slowly walk forward": "a person slowly walks forward",
             "bring the box": "a person brings the box", "touch your toes": "a person touches their toes",
             "walks forward": "a person walks forward"}
    assert {text: as_sentence(text) for text in cases} == cases
    for text in ("a person jumps", "The man runs", "she waves", "someone bows", "", "  ", "3 steps forward"):
        assert as_sentence(text) == text  # descriptions and non-commands are left alone
    assert [third_person(v) for v in ("fly", "play", "cross", "go", "be", "punch")] == \
        ["flies", "plays", "crosses", "goes", "is", "punches"]


def test_the_cache_encodes_each_prompt_once_and_keeps_the_last_ones():
    encoder, cache = _Encoder(), TextCache()
    first = cache.embeddings(["a walk", "a long slow walk", "a walk"], encoder)
    assert encoder.calls == [["a walk", "a long slow walk"]]  # one row per prompt, duplicates encoded once
    assert [int(m.sum()) for m in first.mask] == [2, 4, 2] and first.tokens.shape[:2] == (3, 4)
    again = cache.embeddings(["a long slow walk", "a run"], encoder)
    assert encoder.calls[1:] == [["a run"]]
    assert torch.equal(again.pooled[0], first.pooled[1])
    cache.SIZE = 2
    cache.embeddings(["a jump"], encoder)
    assert list(cache) == ["a run", "a jump"]  # the least recently used went


def test_a_command_generates_the_take_of_its_sentence_and_the_switch_turns_that_off(tmp_path):
    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model

    pipe = MLDPipeline.from_pretrained(tiny_model(tmp_path / "tiny"))
    command, sentence = (pipe([p], 1.5, seed=3).joints for p in ("kick", "a person kicks"))
    assert torch.equal(torch.as_tensor(command), torch.as_tensor(sentence))
    pipe.config.commands_as_sentences = False
    pipe.clear_text_cache()
    assert not torch.equal(torch.as_tensor(pipe(["kick"], 1.5, seed=3).joints), torch.as_tensor(sentence))


@pytest.mark.parametrize("bad", [1, "yes", None])
def test_the_switch_is_checked_when_a_folder_loads(tmp_path, bad):
    import json

    from mld_core.checkpoint import CheckpointError, load_config
    from mld_core.testing import tiny_model

    folder = tiny_model(tmp_path / "m")
    data = json.loads((folder / "config.json").read_text())
    data["commands_as_sentences"] = bad
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises((CheckpointError, ValueError), match="commands_as_sentences must be true or false"):
        load_config(folder)

"""Local SmolVLM directories for building SmolVLA without the model hub.

SmolVLA reads its VLM backbone (config, tokenizer, image/video processors) from `vlm_model_name`, a hub id
or a local directory. Offline there is no hub, so this module writes such a directory itself: a config of
the chosen size and a word-level tokenizer trained with the `tokenizers` library on the task's own
vocabulary. With `load_vlm_weights=False` SmolVLA then initialises the VLM at random, which is what the
CPU tests (tiny size) and the latency benchmark (full SmolVLM2-500M size) need.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vla_ladder import files
from vla_ladder.task.objects import OBJECT_NAMES, instruction_for

# The tokens SmolVLM's processor and SmolVLA look up by name.
SPECIAL_TOKENS = {
    "pad_token": "<pad>",
    "unk_token": "<unk>",
    "bos_token": "<|im_start|>",
    "eos_token": "<end_of_utterance>",
}
EXTRA_SPECIAL_TOKENS = {
    "fake_image_token": "<fake_token_around_image>",
    "image_token": "<image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
}


@dataclass(frozen=True)
class VLMSize:
    """Architecture of the SmolVLM backbone (text model = Llama, vision model = SigLIP-like)."""

    text_hidden: int
    text_layers: int
    text_heads: int
    text_kv_heads: int
    text_intermediate: int
    vision_hidden: int
    vision_layers: int
    vision_heads: int
    vision_intermediate: int
    image_size: int
    """Side of the square image the vision tower sees; SmolVLA's resize_imgs_with_padding must match."""
    patch_size: int
    scale_factor: int
    vocab_pad_to: int = 0
    """Pad the vocabulary to this size (0: keep the trained tokenizer's size)."""


TINY = VLMSize(text_hidden=64, text_layers=2, text_heads=4, text_kv_heads=2, text_intermediate=128,
               vision_hidden=32, vision_layers=1, vision_heads=2, vision_intermediate=64,
               image_size=64, patch_size=16, scale_factor=2)
# Big enough to tell five objects apart at 128x128 (16 image tokens a camera), small enough (~3M parameters) to
# train from scratch on a CPU in minutes: the backbone of the study presets' SmolVLA-scratch.
SMALL = VLMSize(text_hidden=128, text_layers=4, text_heads=4, text_kv_heads=2, text_intermediate=256,
                vision_hidden=128, vision_layers=4, vision_heads=4, vision_intermediate=256,
                image_size=128, patch_size=16, scale_factor=2)
# SMALL at 64x64 (4 image tokens a camera): on a 2-core CPU it trains ~2.5x faster than at 128 and learned more
# in the same time (benchmarks/results/study_cpu_mini/tuning.json): the backbone of the cpu-mini preset.
SMALL64 = VLMSize(**{**SMALL.__dict__, "image_size": 64})
# SmolVLM2-500M-Video-Instruct, the backbone of lerobot/smolvla_base, as in its public config.json.
SMOLVLM2_500M = VLMSize(text_hidden=960, text_layers=32, text_heads=15, text_kv_heads=5, text_intermediate=2560,
                        vision_hidden=768, vision_layers=12, vision_heads=12, vision_intermediate=3072,
                        image_size=512, patch_size=16, scale_factor=4, vocab_pad_to=49280)
SIZES = {"tiny": TINY, "small": SMALL, "small64": SMALL64, "smolvlm2-500m": SMOLVLM2_500M}


def _corpus() -> list[str]:
    """Every wording of every instruction set (training and held-out): a word a policy never trained on still
    gets its own token, whose embedding stays where initialisation left it."""
    from vla_ladder.contract import BLIND_INSTRUCTION
    from vla_ladder.task.instructions import INSTRUCTION_SETS, wordings
    words = [instruction_for(name) for name in OBJECT_NAMES] + [BLIND_INSTRUCTION]
    words += [w.text for name in OBJECT_NAMES for s in INSTRUCTION_SETS for w in wordings(name, s)]
    words += ["Assistant:", "User:", "\n"]
    return words


def build_vlm_dir(out: str | Path, size: str | VLMSize = "tiny") -> Path:
    """Write a SmolVLM config + tokenizer + processors to `out` (idempotent) and return it."""
    from tokenizers import Tokenizer, models, pre_tokenizers, trainers
    from transformers import (PreTrainedTokenizerFast, SmolVLMConfig, SmolVLMImageProcessor, SmolVLMProcessor,
                              SmolVLMVideoProcessor)

    if isinstance(size, str):
        if size not in SIZES:
            raise ValueError(f"unknown VLM size {size!r}; allowed: {', '.join(SIZES)}")
        size = SIZES[size]
    out = Path(out)
    if (out / "config.json").is_file() and (out / "tokenizer.json").is_file():
        return out

    specials = list(dict.fromkeys([*SPECIAL_TOKENS.values(), *EXTRA_SPECIAL_TOKENS.values()]))
    tok = Tokenizer(models.WordLevel(unk_token=SPECIAL_TOKENS["unk_token"]))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.train_from_iterator(_corpus(), trainers.WordLevelTrainer(special_tokens=specials))
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=tok, **SPECIAL_TOKENS,
                                        extra_special_tokens=EXTRA_SPECIAL_TOKENS)
    vocab = max(tokenizer.vocab_size, size.vocab_pad_to)

    image_seq_len = (size.image_size // size.patch_size) ** 2 // size.scale_factor**2
    config = SmolVLMConfig(
        image_token_id=tokenizer.convert_tokens_to_ids(EXTRA_SPECIAL_TOKENS["image_token"]),
        scale_factor=size.scale_factor,
        tie_word_embeddings=False,
        text_config=dict(model_type="llama", vocab_size=vocab, hidden_size=size.text_hidden,
                         num_hidden_layers=size.text_layers, num_attention_heads=size.text_heads,
                         num_key_value_heads=size.text_kv_heads, intermediate_size=size.text_intermediate,
                         head_dim=size.text_hidden // size.text_heads, max_position_embeddings=8192,
                         rms_norm_eps=1e-5, pad_token_id=tokenizer.pad_token_id),
        vision_config=dict(hidden_size=size.vision_hidden, num_hidden_layers=size.vision_layers,
                           num_attention_heads=size.vision_heads, intermediate_size=size.vision_intermediate,
                           image_size=size.image_size, patch_size=size.patch_size),
    )
    edge = {"longest_edge": size.image_size}
    processor = SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(size=edge, max_image_size=edge),
        tokenizer=tokenizer,
        video_processor=SmolVLMVideoProcessor(size=edge, max_image_size=edge),
        image_seq_len=image_seq_len,
    )
    with files.atomic_dir(out) as tmp:  # the check above trusts two of its files: the rest must be there with them
        config.save_pretrained(tmp)
        processor.save_pretrained(tmp)
    return out


def scratch_smolvla_args(vlm_dir: str | Path, image_size: int) -> list[str]:
    """LeRobot flags that train SmolVLA from scratch on the VLM directory `vlm_dir` (see `build_vlm_dir`).

    With random VLM weights nothing may stay frozen: SmolVLA's defaults train only the action expert on top
    of a pretrained backbone. Images are resized to the VLM's own side instead of SmolVLA's 512.
    """
    return [f"--policy.vlm_model_name={vlm_dir}", "--policy.load_vlm_weights=false",
            "--policy.train_expert_only=false", "--policy.freeze_vision_encoder=false",
            f"--policy.resize_imgs_with_padding=[{image_size},{image_size}]"]

"""Text tokenizers: an offline byte-level BPE for the tiny preset; any tokenizer from a local folder.

Vocabulary rule: the tiny LM has `len(tokenizer) + 256` embedding rows, the 256 ids after the tokenizer's
vocabulary being reserved for actions (model/language/action_tokenizer.py). Llama-2's own tokenizer is loaded from
a local folder only; nothing is downloaded.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

from openfly_agent.model.config import NUM_ACTION_SLOTS

logger = logging.getLogger(__name__)

BOS_TOKEN = "<s>"
EOS_TOKEN = "</s>"
PAD_TOKEN = "<pad>"
UNK_TOKEN = "<unk>"
SPECIAL_TOKENS = (UNK_TOKEN, BOS_TOKEN, EOS_TOKEN, PAD_TOKEN)  # ids 0..3 (unk 0, bos 1, eos 2 as in Llama)


def train_bpe_tokenizer(texts: Iterable[str], vocab_size: int, out_dir: str | Path | None = None):
    """Train a byte-level BPE tokenizer on `texts` offline (HF `tokenizers`), with BOS / EOS / PAD / UNK.

    Encoding adds BOS (as Llama does) and never EOS. Byte-level pre-tokenisation means no text is ever UNK.

    Args:
        texts: training corpus, e.g. the instructions of the training split.
        vocab_size: the most tokens (specials + 256 byte symbols + merges); the corpus may yield fewer.
        out_dir: when given, the tokenizer is saved there (`save_pretrained` layout) as well.

    Returns:
        A `transformers` fast tokenizer.
    """
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast

    minimum = len(SPECIAL_TOKENS) + 256
    if vocab_size < minimum:
        raise ValueError(f"vocab_size={vocab_size} is too small for byte-level BPE: use >= {minimum}")
    tokenizer = Tokenizer(models.BPE(unk_token=UNK_TOKEN))
    tokenizer.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=True)
    tokenizer.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=list(SPECIAL_TOKENS),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tokenizer.train_from_iterator(texts, trainer=trainer)
    bos_id = tokenizer.token_to_id(BOS_TOKEN)
    tokenizer.post_processor = processors.TemplateProcessing(
        single=f"{BOS_TOKEN} $A", pair=f"{BOS_TOKEN} $A $B", special_tokens=[(BOS_TOKEN, bos_id)]
    )
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tokenizer,
        bos_token=BOS_TOKEN,
        eos_token=EOS_TOKEN,
        pad_token=PAD_TOKEN,
        unk_token=UNK_TOKEN,
        padding_side="right",
    )
    logger.info("trained a byte-level BPE tokenizer with %d tokens", len(fast))
    if out_dir is not None:
        fast.save_pretrained(str(out_dir))
    return fast


def load_tokenizer(folder: str | Path):
    """Load a tokenizer saved with `save_pretrained` (ours or Llama-2's) from a local folder only."""
    from transformers import AutoTokenizer, PreTrainedConfig

    path = Path(folder)
    if not path.is_dir():
        raise FileNotFoundError(
            f"tokenizer folder {path} does not exist (llm.tokenizer_path must be a local folder)"
        )
    # A blank config: the class comes from tokenizer_config.json, not from a model config.json beside it
    # (an agent checkpoint's model_type is unknown to AutoConfig unless registered).
    tokenizer = AutoTokenizer.from_pretrained(str(path), config=PreTrainedConfig(), local_files_only=True)
    if tokenizer.pad_token_id is None:
        raise ValueError(f"tokenizer in {path} has no pad token: add one (OpenVLA adds <PAD> to Llama-2's)")
    return tokenizer


# Files a saved tokenizer may consist of (ours: tokenizer.json; Llama-2's: tokenizer.model).
TOKENIZER_FILES = ["tokenizer*", "special_tokens_map.json", "added_tokens.json", "vocab*", "merges.txt"]


def tokenizer_folder(name_or_path: str, hub_kwargs: dict) -> Path | None:
    """Local folder holding a checkpoint's tokenizer, fetching only the tokenizer files of a Hub repo id
    (with the `revision` / `token` / `cache_dir` / `local_files_only` of `hub_kwargs`). None when it has none."""
    folder = Path(name_or_path)
    if folder.is_dir():
        return folder if (folder / "tokenizer_config.json").is_file() else None
    from huggingface_hub import snapshot_download

    snapshot = Path(
        snapshot_download(
            name_or_path,
            revision=hub_kwargs.get("revision"),
            cache_dir=hub_kwargs.get("cache_dir"),
            token=hub_kwargs.get("token"),
            local_files_only=bool(hub_kwargs.get("local_files_only", False)),
            allow_patterns=TOKENIZER_FILES,
        )
    )
    return snapshot if (snapshot / "tokenizer_config.json").is_file() else None


def tiny_vocab_size(tokenizer) -> int:
    """Embedding rows of the tiny LM for `tokenizer`: its length + the 256 reserved action ids."""
    return len(tokenizer) + NUM_ACTION_SLOTS

"""The per-GPU memory estimate (training/memory_estimate.py): hand-checked arithmetic, the shipped 7B configs'
figures against what one H200 measured, and the one-line refusal."""

from __future__ import annotations

import dataclasses

import pytest
from conftest import REPO_ROOT

from openfly_agent.training.config import TrainConfig
from openfly_agent.training.memory_estimate import (
    CUDA_RESERVE_BYTES,
    GIB,
    HOST_MEMORY_USABLE,
    ModelSizes,
    Sharding,
    activation_bytes,
    check_memory,
    describe_run,
    estimate_memory,
    host_memory_bytes,
    model_sizes,
    refuse_if_too_big,
)
from openfly_agent.training.preflight import PreflightError
from openfly_agent.utils.config import load_yaml_config

OPENVLA_7B_PARAMS = 7_541_237_184  # the released openvla-7b, vision parts the agent prunes included
H200_BYTES = 140 * GIB  # what torch.cuda.mem_get_info reports for a 141 GB H200, about
H100_BYTES = 79 * GIB


def train_config(name: str, *overrides: str) -> TrainConfig:
    return load_yaml_config(TrainConfig, REPO_ROOT / "configs" / "train" / name, list(overrides))


@pytest.fixture(scope="module")
def sizes_7b() -> dict[str, ModelSizes]:
    """The two 7B recipes' agents, counted on the meta device."""
    return {name: model_sizes(train_config(f"openfly-7b-{name}.yaml")) for name in ("lora", "full")}


def no_activations(params: int, trainable: int) -> ModelSizes:
    return ModelSizes(params, trainable, 0, params, 0, 0, 0, (), (), 0, 0, 0)


def test_full_fine_tune_of_openvla_7b_holds_16_bytes_per_parameter():
    # fp32 weights 4 + fp32 gradients 4 + AdamW's two fp32 moments 8 = 16 B: 120.66 GB for 7,541,237,184
    cfg = train_config("openfly-7b-full.yaml")
    estimate = estimate_memory(no_activations(OPENVLA_7B_PARAMS, OPENVLA_7B_PARAMS), cfg, Sharding())
    states = estimate.weights + estimate.gradients + estimate.optimizer
    assert states == 16 * OPENVLA_7B_PARAMS == 120_659_794_944
    assert estimate.optimizer_step == 4 * OPENVLA_7B_PARAMS  # AdamW foreach: one more fp32 copy
    assert estimate.autocast_cache == 2 * OPENVLA_7B_PARAMS  # bf16 copies kept from forward to backward
    # the step's peak: states + the AdamW copy + the reserve = 20 B / parameter + 1 GiB
    assert estimate.peak == 20 * OPENVLA_7B_PARAMS + CUDA_RESERVE_BYTES
    # FSDP over 8 processes: a 1/8 of the states each; offloaded: all of them in host memory
    fsdp = estimate_memory(no_activations(OPENVLA_7B_PARAMS, OPENVLA_7B_PARAMS), cfg, Sharding("fsdp", 8))
    assert fsdp.weights + fsdp.gradients + fsdp.optimizer == 16 * OPENVLA_7B_PARAMS // 8
    offload = estimate_memory(
        no_activations(OPENVLA_7B_PARAMS, OPENVLA_7B_PARAMS), cfg, Sharding("fsdp", 8, offload=True)
    )
    assert offload.weights == offload.optimizer == offload.optimizer_step == 0
    assert offload.host == 16 * OPENVLA_7B_PARAMS


def test_activations_by_hand():
    # 2 Llama layers of width 4, MLP 8, 10 tokens per sample, batch 2 (20 tokens), fp32 residual:
    # per token and layer 2*4*4 + 8*4 + 8*8 = 128 B -> 2560 B per layer; the projector 3 -> 5 -> 4 on
    # 2 frames x 3 patches per sample (12 patches): 12 * 2 B * (3 + 5) = 192 B
    sizes = ModelSizes(0, 0, 0, 0, 2, 4, 8, (), (3, 5, 4), 10, 2, 3)
    assert activation_bytes(sizes, batch=2, checkpointing=False, residual_bytes=4) == 2 * 2560 + 192
    # checkpointed: each layer's input (20 tokens x 4 x 4 B = 320 B) + one layer recomputed
    assert activation_bytes(sizes, batch=2, checkpointing=True, residual_bytes=4) == 2 * 320 + 2560 + 192
    # one trained ViT block of width 2, MLP 4, 5 tokens per frame, on 4 frames: 20 * (2*4*2 + 8*2 + 4*4) = 960
    vit = dataclasses.replace(sizes, vit_blocks=((2, 4, 5),))
    assert activation_bytes(vit, batch=2, checkpointing=False, residual_bytes=4) == 2 * 2560 + 960 + 192


def test_the_7b_recipes_counted_on_the_meta_device(sizes_7b):
    lora, full = sizes_7b["lora"], sizes_7b["full"]
    # the 7B LoRA bench on an H200 reported 7.58 B parameters, 155 M trainable (docs/BENCHMARKS.md)
    assert round(lora.params / 1e9, 2) == 7.58 and round(lora.trainable / 1e6) == 155
    assert full.trainable == full.params  # freeze_stage full
    assert 7.4e9 < full.params < OPENVLA_7B_PARAMS  # the pruned ViT blocks are not part of the agent
    assert lora.llm_layers == 32 and lora.llm_hidden == 4096 and lora.vit_blocks == ()  # vision frozen
    assert len(full.vit_blocks) == 23 + 26  # both ViTs train in the full fine-tune (pruned after depth - 2)
    assert lora.tokens_per_sample == 258 + 100 and lora.frames_per_sample == 1 + 2 * 5


def test_counting_reads_no_tokenizer(sizes_7b, tmp_path):
    missing = tmp_path / "no-tokenizer-here"  # the builder reports a bad path later, in its own words
    cfg = train_config("openfly-7b-full.yaml", f"--model.llm.tokenizer_path={missing}")
    assert model_sizes(cfg) == sizes_7b["full"]


def test_lora_on_one_gpu_is_a_lower_bound_of_the_measured_peak(sizes_7b):
    estimate = estimate_memory(sizes_7b["lora"], train_config("openfly-7b-lora.yaml"), Sharding())
    measured = 54.5 * GIB  # bench/train_throughput.py's 7b-lora-bf16 on one H200, batch 8
    assert 0.55 * measured < estimate.peak < measured  # 33.1 GiB: weights 28.2 of it
    assert estimate.weights == 4 * sizes_7b["lora"].params
    refuse_if_too_big(estimate, Sharding(), [H100_BYTES], "lora")  # fits one 80 GB GPU: no error


def test_full_fine_tune_on_one_gpu_is_refused_in_one_line(sizes_7b):
    cfg = train_config("openfly-7b-full.yaml")
    one = Sharding(
        "fsdp", 1, activation_checkpointing=True
    )  # fsdp.yaml with --num_processes 1, as in issue 38
    estimate = estimate_memory(sizes_7b["full"], cfg, one)
    assert estimate.peak > H200_BYTES  # it ran out of memory in its first AdamW step on one H200
    run = describe_run(cfg, "configs/train/openfly-7b-full.yaml")
    assert run == (
        "configs/train/openfly-7b-full.yaml: llama2-7b, freeze_stage=full, precision=bf16, per-device batch 16"
    )
    with pytest.raises(PreflightError) as err:
        refuse_if_too_big(estimate, one, [H200_BYTES], run)
    message = str(err.value)
    assert "\n" not in message
    assert f"this run ({run}) needs at least 141 GiB per GPU with 1 process(es) (fsdp)" in message
    assert "fsdp_offload.yaml" in message
    assert f"{estimate.peak / GIB:.0f} GiB" in message and "--num_processes N" in message


def test_offloading_more_than_the_host_holds_is_refused_in_one_line(sizes_7b):
    cfg = train_config("openfly-7b-full.yaml")
    offload = Sharding("fsdp", 1, offload=True, activation_checkpointing=True)
    estimate = estimate_memory(sizes_7b["full"], cfg, offload)
    assert estimate.host == 16 * sizes_7b["full"].params  # fp32 weights + gradients + two AdamW moments
    assert round(estimate.host / GIB, 1) == 111.8
    run = describe_run(cfg, "configs/train/openfly-7b-full.yaml")
    # the H200 machine that killed this run in its first step had 128 GiB: 111.8 > 0.85 * 128 = 108.8
    with pytest.raises(PreflightError) as err:
        refuse_if_too_big(estimate, offload, [H200_BYTES], run, host_bytes=128 * GIB)
    message = str(err.value)
    assert "\n" not in message
    assert (
        f"this run ({run}) keeps at least 112 GiB of model states in host memory with 1 process(es)"
        in message
    )
    assert "more than 85% of the 128 GiB this machine has" in message and "fsdp_multinode.yaml" in message
    refuse_if_too_big(estimate, offload, [H200_BYTES], run, host_bytes=256 * GIB)  # room: no error
    refuse_if_too_big(estimate, offload, [H200_BYTES], run)  # host unknown: the GPU check alone
    # a run that offloads nothing is never refused for its host, however small
    lora = estimate_memory(sizes_7b["lora"], train_config("openfly-7b-lora.yaml"), Sharding())
    refuse_if_too_big(lora, Sharding(), [H200_BYTES], "lora", host_bytes=1 * GIB)
    assert HOST_MEMORY_USABLE * 128 * GIB < estimate.host < HOST_MEMORY_USABLE * 132 * GIB


def test_host_memory_is_the_lower_of_the_machine_and_its_cgroup(tmp_path):
    physical = host_memory_bytes(tmp_path / "no-cgroup-file")
    assert physical > 0
    limit = tmp_path / "memory.max"
    limit.write_text("max\n")  # cgroup v2 without a limit
    assert host_memory_bytes(limit) == physical
    limit.write_text(f"{GIB}\n")
    assert host_memory_bytes(limit) == GIB
    limit.write_text(f"{physical * 2}\n")
    assert host_memory_bytes(limit) == physical


@pytest.mark.parametrize(
    ("sharding", "gpu_bytes", "fits"),
    [
        (Sharding("fsdp", 8, activation_checkpointing=True), H100_BYTES, True),  # the paper's 8 GPUs
        (Sharding("fsdp", 4, activation_checkpointing=True), H100_BYTES, True),
        (Sharding("fsdp", 1, offload=True, activation_checkpointing=True), H100_BYTES, True),
        (Sharding("zero3", 8, offload=True), H100_BYTES, False),  # the full config has no checkpointing
    ],
)
def test_where_the_full_fine_tune_fits(sizes_7b, sharding, gpu_bytes, fits):
    estimate = estimate_memory(sizes_7b["full"], train_config("openfly-7b-full.yaml"), sharding)
    assert (estimate.peak <= gpu_bytes) == fits, estimate.summary()


def test_nothing_is_estimated_on_the_cpu():
    from accelerate import Accelerator
    from conftest import reset_accelerate

    reset_accelerate()
    try:
        assert check_memory(train_config("tiny.yaml"), Accelerator(cpu=True)) is None
    finally:
        reset_accelerate()

"""Keys, ids and file names shared by every part of the package (one meaning everywhere, docs/CONVENTIONS.md)."""

from __future__ import annotations

# --- Action codebook (OpenFly ids; the executed motion lives in sim/dynamics.py) -------------------
ACTION_STOP = 0
ACTION_FORWARD = 1
ACTION_TURN_LEFT = 2
ACTION_TURN_RIGHT = 3
ACTION_ASCEND = 4
ACTION_DESCEND = 5
ACTION_MOVE_LEFT = 6
ACTION_MOVE_RIGHT = 7
ACTION_FORWARD_6 = 8
ACTION_FORWARD_9 = 9
# Released annotations also hold these two phases; the model never emits them.
ACTION_TAKEOFF = -1  # 3 m climb before the navigation segment
ACTION_LANDING = -2  # 3 m descent after STOP

NUM_ACTIONS = 10  # ids 0..9, what the model predicts
MODEL_ACTION_IDS = tuple(range(NUM_ACTIONS))
ALL_ACTION_IDS = (ACTION_LANDING, ACTION_TAKEOFF, *MODEL_ACTION_IDS)

ACTION_NAMES: dict[int, str] = {
    ACTION_LANDING: "landing",
    ACTION_TAKEOFF: "takeoff",
    ACTION_STOP: "stop",
    ACTION_FORWARD: "forward",
    ACTION_TURN_LEFT: "turn left",
    ACTION_TURN_RIGHT: "turn right",
    ACTION_ASCEND: "ascend",
    ACTION_DESCEND: "descend",
    ACTION_MOVE_LEFT: "move left",
    ACTION_MOVE_RIGHT: "move right",
    ACTION_FORWARD_6: "forward 6",
    ACTION_FORWARD_9: "forward 9",
}

STEP_METERS = 3.0  # forward / vertical / lateral primitive
TURN_DEGREES = 30.0  # one turn primitive

# --- Episodes and metrics --------------------------------------------------------------------------
SUCCESS_RADIUS_M = 20.0
MAX_EPISODE_STEPS = 100
CAMERA_HFOV_DEG = 90.0
HIGH_CATEGORY_PITCH_DEG = -45.0  # camera pitch for trajectories of the `high_*` categories

SPLIT_TRAIN = "train"
SPLIT_TEST_SEEN = "test_seen"
SPLIT_TEST_UNSEEN = "test_unseen"
# Generated datasets only: routes of the train cities kept out of training plus a validation city of their own,
# what choices are made on (the released OpenFly data has no such split; docs/TOOLCHAIN.md, "Splits")
SPLIT_VAL = "val"
SPLITS = (SPLIT_TRAIN, SPLIT_TEST_SEEN, SPLIT_TEST_UNSEEN, SPLIT_VAL)
# The annotation file of each split (the first three are the released OpenFly files).
ANNOTATION_FILES = {
    SPLIT_TRAIN: "train.json",
    SPLIT_TEST_SEEN: "seen.json",
    SPLIT_TEST_UNSEEN: "unseen.json",
    SPLIT_VAL: "val.json",
}
RELEASED_DATA_CARD = "data_cards/openfly_released.md"  # how to download the released OpenFly data

# --- Training batch keys (the contract between data/ collator and model/ agent) -------------------
# Pixel tensors are uint8 RGB at the model's input size; the model normalises them itself.
INPUT_IDS = "input_ids"  # (B, L) long: [BOS] prompt tokens, then the action token(s); right padded
ATTENTION_MASK = "attention_mask"  # (B, L) long
LABELS = "labels"  # (B, L) long, -100 everywhere but the action token(s)
PIXEL_VALUES = "pixel_values"  # (B, 3, H, W) uint8, current frame
MEMORY_PIXEL_VALUES = "memory_pixel_values"  # (B, K, S, 3, H, W) uint8, keyframe sets oldest first
TARGET_ATTRIBUTES = "target_attributes"  # (B, 4) long: target's colour, type, size, feature ids (-1: unknown)
# grounding batches: every visible landmark of each row's frame (expression frames; none on instruction rows)
MEMORY_FRAME_MASK = "memory_frame_mask"  # (B, K, S) bool, frame s of set k is real
MEMORY_BOXES = "memory_boxes"  # (B, K, S, 4) float, (cx, cy, w, h) in [0, 1]
MEMORY_BOX_VISIBLE = "memory_box_visible"  # (B, K, S) bool
BOX = "box"  # (B, 4) float, current frame landmark box (cx, cy, w, h)
BOX_VISIBLE = "box_visible"  # (B,) bool; False = no landmark visible (mask, never a fake box)
# optional: the box the box token embeds when it is not `box` (the RL stage: the box the policy predicted while
# it flew, so the recorded step replays what the policy saw; `box` stays the grounding target)
TOKEN_BOX = "token_box"  # (B, 4) float (cx, cy, w, h)
TOKEN_BOX_VISIBLE = "token_box_visible"  # (B,) bool
FRAME_INDEX = "frame_index"  # (B,) long: the frame of `pixel_values` each sequence reads (grounding batches)
ACTION = "action"  # (B,) long, action id 0..9
ACTION_VECTOR = "action_vector"  # (B, 8) float, openvla_bins head only
EPISODE_ID = "episode_id"  # list[str]
STEP_INDEX = "step_index"  # (B,) long
MEMORY = (
    "memory"  # dataset sample only: K keyframe sets, each a list of (rgb, box, box_visible), oldest first
)

IGNORE_INDEX = -100

# --- Landmark attributes (TARGET_ATTRIBUTES / LANDMARK_ATTRIBUTES ids index these tuples) ------------
# The embedded city draws its landmarks from these closed vocabularies (sim/city_vocab.py gives them their
# render materials); instructions name only these words. The order is the class id order of each attribute.
LANDMARK_ATTRIBUTE_FIELDS = ("color", "type", "size", "feature")  # the `Landmark` fields, in id order
LANDMARK_COLORS = (
    "red", "orange", "yellow", "green", "blue", "purple", "pink", "white", "gray", "black", "brown", "beige",
)  # fmt: skip
LANDMARK_TYPES = ("house", "warehouse", "building", "office building", "tower", "skyscraper")
LANDMARK_SIZES = ("low-rise", "mid-rise", "high-rise")  # height classes (sim/city_vocab.py: metres)
LANDMARK_FEATURES = (
    "none",
    "rooftop billboard",
    "spire",
    "dome",
    "antenna",
    "water tank",
    "rooftop garden",
    "glass facade",
)
LANDMARK_VOCABULARIES = (LANDMARK_COLORS, LANDMARK_TYPES, LANDMARK_SIZES, LANDMARK_FEATURES)  # field order

# --- Observation keys (simulator -> agent) ---------------------------------------------------------
OBS_RGB = "rgb"  # (H, W, 3) uint8
OBS_POSE = "pose"  # (4,) float (x, y, z, yaw)
OBS_BOXES = "boxes"  # dict landmark_id -> (cx, cy, w, h)
OBS_DEPTH = "depth"  # (H, W) float metres
OBS_INSTRUCTION = "instruction"

# --- Memory probe (eval.py --agent.memory_probe) ----------------------------------------------------
# What the agent's memory read returns at inference: `none` its memory (the model as trained), `empty` no memory
# token at any step (the episode still remembers its keyframes: only the read is emptied), so a paired comparison
# of the two runs says whether the memory changes what the agent does (docs/EVAL.md, "Memory probe").
MEMORY_PROBE_NONE = "none"
MEMORY_PROBE_EMPTY = "empty"
MEMORY_PROBES = (MEMORY_PROBE_NONE, MEMORY_PROBE_EMPTY)

# --- File names -------------------------------------------------------------------------------------
CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
WEIGHTS_INDEX_NAME = "model.safetensors.index.json"
ACTION_TOKENIZER_NAME = "action_tokenizer.json"
NORM_STATS_NAME = "dataset_statistics.json"
TRAIN_CONFIG_NAME = "train_config.json"
TRAINER_STATE_NAME = "trainer_state.json"  # a checkpoint's step counters (training/state.py)
# Training stages (train_config.json `stage`): the grounding stage trains no action head, so only a navigation
# stage's checkpoint is an agent.
STAGE_GROUNDING, STAGE_NAVIGATION = "grounding", "navigation"
STAGE_RL = (
    "rl"  # reinforcement fine-tuning of a navigation checkpoint in the simulator (training/rl_trainer.py)
)
MODEL_CARD_NAME = "README.md"
ADAPTER_DIR_NAME = "adapter"
PROCESSOR_CONFIG_NAME = "processor_config.json"  # OpenFlyProcessor's settings (transformers' name)
# A training run: <output_dir>/checkpoints/step-NNNNNN/ folders and `last`, a relative symlink to the newest.
CHECKPOINTS_DIR = "checkpoints"
LAST_POINTER_NAME = "last"
# `checkpoint.keep_best`: `best`, a relative symlink to the step folder of the best validation pass so far
BEST_POINTER_NAME = "best"
MERGED_DIR_NAME = "merged"  # <output_dir>/merged: a LoRA run's adapter merged into its base at the end

EPISODES_JSONL = "episodes.jsonl"
RESULTS_JSON = "results.json"
RESULTS_MD = "results.md"
DATASET_INFO_JSON = "meta/info.json"
DATASET_STATS_JSON = "meta/stats.json"
# Dataset root layout (mirrors the released OpenFly data; data/writer.py, data/openfly_reader.py)
DATASET_TRAJ_DIR = "traj"  # traj/<scene>/astar_data/<category>/<folder>.parquet, one per trajectory
DATASET_ANNOTATION_DIR = "Annotation"  # Annotation/{train,seen,unseen,val}.json
DATASET_PARTS_DIR = "Annotation/parts"  # Annotation/parts/<split>/<scene>.json, merged by finalize()
DATASET_SCHEMA_VERSION = 1
# The toolchain's own records inside a generated dataset root (toolchain/ledger.py, toolchain/summary.py)
TOOLCHAIN_UNITS_DIR = "meta/toolchain/units"  # units/<scene>.jsonl: one line per finished work unit
TOOLCHAIN_SUMMARY_JSON = "meta/toolchain/summary.json"  # the paper's statistics of the dataset
TOOLCHAIN_SUMMARY_PNG = "meta/toolchain/summary.png"
TOOLCHAIN_CONFIG_JSON = "meta/toolchain/generate_config.json"
# What the readers of a generated dataset need of its settings (frame size, city), data/generation_settings.py
GENERATION_SETTINGS_JSON = "meta/generation_settings.json"

MODEL_TYPE = "openfly_agent"

# --- The official 8-dim action vectors of the released OpenFly-Agent (docs/OFFICIAL_OPENFLY.md section 2) ----
# dims: 0 stop, 1 forward metres (3/6/9), 2 turn left, 3 turn right, 4 up, 5 down, 6 move left, 7 move right.
# The magnitudes (15, 2, 5) are codes inherited from AerialVLN, not the executed motion (30 deg, 3 m, 3 m).
OPENVLA_ACTION_DIM = 8
OPENVLA_ACTION_VECTORS: dict[int, tuple[float, ...]] = {
    ACTION_STOP: (1, 0, 0, 0, 0, 0, 0, 0),
    ACTION_FORWARD: (0, 3, 0, 0, 0, 0, 0, 0),
    ACTION_TURN_LEFT: (0, 0, 15, 0, 0, 0, 0, 0),
    ACTION_TURN_RIGHT: (0, 0, 0, 15, 0, 0, 0, 0),
    ACTION_ASCEND: (0, 0, 0, 0, 2, 0, 0, 0),
    ACTION_DESCEND: (0, 0, 0, 0, 0, 2, 0, 0),
    ACTION_MOVE_LEFT: (0, 0, 0, 0, 0, 0, 5, 0),
    ACTION_MOVE_RIGHT: (0, 0, 0, 0, 0, 0, 0, 5),
    ACTION_FORWARD_6: (0, 6, 0, 0, 0, 0, 0, 0),
    ACTION_FORWARD_9: (0, 9, 0, 0, 0, 0, 0, 0),
}

"""Whether the landmark an instruction is talking about is in view: what a memory-free agent can see.

Per trajectory, from what the toolchain knows when it writes the instruction (`InstructionRequest`: the
labels, every landmark's box per frame, the route's targets and the frame where each leg ends):

- decision steps: the frames whose label is a model action (navigation and the final STOP; take-off and
  landing frames are not decisions of the agent);
- the current clause of decision step t: the instruction's sub-trajectories are exactly the template's
  (`split_at_transitions` -> `merge_short_segments` -> `assign_landmarks`), segment [start, end) carrying
  the labels of frames start..end-1; the current clause is the first segment with end > t (the one being
  flown, or the next one where merging dropped a cancelled jog), and after the last segment the closing
  "stop at <target>" clause, whose landmark is the final target;
- its landmark: the landmark whose position decides the clause's action (`segments.deciding_landmark`): in
  a clause "after passing <X>, ..." (`instructions.name_passed_landmark`) the target X just reached, which
  says when the action is due; otherwise the landmark the clause names: the segment's `landmark_id` (a leg
  target where a leg ends, else the landmark seen where it ends) for forward runs and turns; a clause that
  names none (climbs and descents, or nothing seen) does not count;
- the current leg of decision step t: the first leg whose end frame is after t (the STOP frame: the last);
- hidden: the landmark has no box in frame t (the renderer records a box for every landmark in view, above
  `render.min_box_pixels`); unseen: hidden, or its box covers less than `instructions.min_box_area` of the
  frame (the size at which the instruction generator calls a landmark seen).

`route_visibility` counts them; `summary.py` pools the counts over a dataset, so a share is over decision
steps, not a mean of per-route shares.
"""

from __future__ import annotations

from openfly_agent.toolchain.instructions.segments import (
    LANDING,
    NAMING_KINDS,
    TAKEOFF,
    InstructionRequest,
    assign_landmarks,
    box_area,
    deciding_landmark,
    merge_short_segments,
    split_at_transitions,
)
from openfly_agent.toolchain.render import leg_of_frame


def _unseen(landmark_id: str, boxes: dict, min_area: float) -> bool:
    return landmark_id not in boxes or box_area(boxes[landmark_id]) < min_area


def route_visibility(request: InstructionRequest) -> dict[str, int]:
    """Counts of one trajectory (see the module docstring).

    Returns:
        decision_steps: frames with a model action (STOP included);
        clause_steps: those whose current clause names a landmark;
        clause_hidden / clause_unseen: ... of which that landmark is hidden / unseen in the frame;
        leg_hidden / leg_unseen: decision steps whose current leg's target is hidden / unseen in the frame;
        targets_named: 1 when the clauses that name route targets name each one, in order (a target whose
            leg end falls in a climb, or in the same clause as the next target's, is left unnamed), else 0.
    """
    segments = merge_short_segments(split_at_transitions(request.actions), request.merge_short_m)
    nav = [s for s in assign_landmarks(request, segments) if s.kind not in (TAKEOFF, LANDING)]
    named = [s.landmark_id for s in nav if s.forced and s.kind in NAMING_KINDS]
    if not named or named[-1] != request.target_ids[-1]:
        named.append(request.target_ids[-1])  # the closing "stop at <target>" clause names it
    counts = dict.fromkeys(("decision_steps", "clause_steps", "clause_hidden", "clause_unseen"), 0)
    counts.update(leg_hidden=0, leg_unseen=0)
    for t, action in enumerate(request.actions):
        if int(action) < 0:
            continue
        boxes = request.frame_boxes[t]
        clause = next((s for s in nav if s.end > t), None)
        if clause is None:
            landmark = request.target_ids[-1]
        else:
            landmark = deciding_landmark(clause)
        leg = leg_of_frame(request.leg_end_frames, t)
        counts["decision_steps"] += 1
        if landmark is not None:
            counts["clause_steps"] += 1
            counts["clause_hidden"] += landmark not in boxes
            counts["clause_unseen"] += _unseen(landmark, boxes, request.min_box_area)
        counts["leg_hidden"] += request.target_ids[leg] not in boxes
        counts["leg_unseen"] += _unseen(request.target_ids[leg], boxes, request.min_box_area)
    counts["targets_named"] = int(named == list(request.target_ids))
    return counts

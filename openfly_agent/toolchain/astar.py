"""A* in the action space: 3 m steps at 12 headings of 30 deg, 3 m climb / descend, a turn penalty.

Follows the official "hybridAStar" (docs/OFFICIAL_OPENFLY.md 7.4): 14 neighbours per state, edge cost
3 m + a penalty, Euclidean heuristic, goal reached within 3.1 m, visited states keyed by their position on a
1 m grid. Headings are counted from the start yaw, so the path converts to turn / forward / climb primitives
that `sim/dynamics.py` replays exactly. The inner loop is plain Python over a flat byte view of the dilated
occupancy (one index computation per probe), which is several times faster than numpy per neighbour.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from openfly_agent import constants as C
from openfly_agent.toolchain.config import PlannerConfig
from openfly_agent.toolchain.voxel_map import PlanningMap
from openfly_agent.utils.geometry import Pose

NUM_HEADINGS = int(round(360.0 / C.TURN_DEGREES))  # 12
_UP, _DOWN = NUM_HEADINGS, NUM_HEADINGS + 1  # move codes after the 12 horizontal headings


class PlanningFailed(RuntimeError):
    """No route: `reason` is one of start_blocked, goal_blocked, no_path, max_expansions."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        super().__init__(f"A* failed ({reason}){': ' + detail if detail else ''}")


@dataclass
class PlanResult:
    """A planned path: primitives 1 (forward 3 m), 2 / 3 (turn), 4 / 5 (climb / descend); no STOP."""

    primitives: list[int]
    positions: np.ndarray  # (M + 1, 3) node positions, start first (the A*'s own floats)
    end_heading: int  # heading index of the last node, counted from the start yaw
    expansions: int
    cost: float


def turns_between(heading: int, new_heading: int) -> int:
    """Signed count of 30 deg turns from `heading` to `new_heading` (+ = left; 180 deg = 6 left)."""
    d = (new_heading - heading) % NUM_HEADINGS
    return d if d <= NUM_HEADINGS // 2 else d - NUM_HEADINGS


class ActionSpaceAStar:
    """Plans on a `PlanningMap`'s dilated grid; states below `min_flight_z` or outside the map are blocked."""

    def __init__(self, pmap: PlanningMap, cfg: PlannerConfig | None = None):
        self.cfg = cfg or PlannerConfig()
        grid = pmap.dilated
        self._occ = np.ascontiguousarray(grid.occupied, dtype=np.uint8).tobytes()
        self._origin = tuple(float(v) for v in grid.origin)
        self._inv_voxel = 1.0 / grid.voxel_size
        self._shape = grid.shape
        self._min_z = pmap.min_flight_z

    def blocked(self, x: float, y: float, z: float) -> bool:
        """True if (x, y, z) is in a dilated obstacle, outside the map or below the flight floor."""
        if z < self._min_z:
            return True
        ox, oy, oz = self._origin
        fx, fy, fz = (x - ox) * self._inv_voxel, (y - oy) * self._inv_voxel, (z - oz) * self._inv_voxel
        nx, ny, nz = self._shape
        if not (0.0 <= fx < nx and 0.0 <= fy < ny and 0.0 <= fz < nz):
            return True
        return self._occ[(int(fx) * ny + int(fy)) * nz + int(fz)] != 0

    def segment_blocked(self, a: np.ndarray, b: np.ndarray) -> bool:
        """True if any sample of a -> b (every half voxel) is blocked."""
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        n = max(2, int(math.ceil(np.linalg.norm(b - a) * 2.0 * self._inv_voxel)) + 1)
        return any(self.blocked(*(a + t * (b - a))) for t in np.linspace(0.0, 1.0, n))

    def plan(self, start: Pose, goal: np.ndarray) -> PlanResult:
        """Shortest action path (turns + forward steps + climbs) from `start` to within tolerance of `goal`.

        Raises:
            PlanningFailed: start / goal blocked, the open set ran empty, or `max_expansions` was reached.
        """
        cfg, step = self.cfg, C.STEP_METERS
        gx, gy, gz = (float(v) for v in goal)
        if self.blocked(start.x, start.y, start.z):
            raise PlanningFailed("start_blocked", f"start {start} is in an obstacle or outside the map")
        if self.blocked(gx, gy, gz):
            raise PlanningFailed("goal_blocked", f"goal {(gx, gy, gz)} is in an obstacle or outside the map")
        yaws = [start.yaw + math.radians(C.TURN_DEGREES) * h for h in range(NUM_HEADINGS)]
        dxy = [(step * math.cos(a), step * math.sin(a)) for a in yaws]
        turn_cost = [
            [cfg.turn_penalty * abs(turns_between(h, h2)) for h2 in range(NUM_HEADINGS)]
            for h in range(NUM_HEADINGS)
        ]
        vertical_cost = step + cfg.vertical_penalty
        res, tol, blocked = cfg.key_resolution_m, cfg.goal_tolerance_m, self.blocked
        heuristic = self._heuristic(yaws, (gx, gy, gz))

        # Node arrays: position, heading, parent, move code that reached it.
        xs, ys, zs, hs, parents, moves, gs = [start.x], [start.y], [start.z], [0], [-1], [-1], [0.0]
        best = {(round(start.x / res), round(start.y / res), round(start.z / res)): 0.0}
        closed: set = set()
        heap = [(heuristic(start.x, start.y, start.z, 0), 0)]
        expansions = 0
        while heap:
            _, node = heapq.heappop(heap)
            x, y, z, h, g = xs[node], ys[node], zs[node], hs[node], gs[node]
            key = (round(x / res), round(y / res), round(z / res))
            if key in closed:
                continue
            closed.add(key)
            if math.dist((x, y, z), (gx, gy, gz)) <= tol:
                return self._result(node, xs, ys, zs, hs, parents, moves, expansions, g)
            expansions += 1
            if expansions > cfg.max_expansions:
                raise PlanningFailed(
                    "max_expansions", f"{cfg.max_expansions} expansions without reaching the goal"
                )
            for move in range(NUM_HEADINGS + 2):
                if move < NUM_HEADINGS:
                    mx, my, mz = x + 0.5 * dxy[move][0], y + 0.5 * dxy[move][1], z  # segment midpoint
                    nx_, ny_, nz_, new_h = x + dxy[move][0], y + dxy[move][1], z, move
                    ng = g + step + turn_cost[h][move]
                else:
                    nz_ = z + (step if move == _UP else -step)
                    mx, my, mz, nx_, ny_, new_h = x, y, 0.5 * (z + nz_), x, y, h
                    ng = g + vertical_cost
                nkey = (round(nx_ / res), round(ny_ / res), round(nz_ / res))
                if (
                    nkey in closed
                    or ng >= best.get(nkey, math.inf)
                    or blocked(nx_, ny_, nz_)
                    or blocked(mx, my, mz)
                ):
                    continue
                best[nkey] = ng
                xs.append(nx_), ys.append(ny_), zs.append(nz_), hs.append(new_h)
                parents.append(node), moves.append(move), gs.append(ng)
                heapq.heappush(heap, (ng + heuristic(nx_, ny_, nz_, new_h), len(xs) - 1))
        raise PlanningFailed("no_path", f"open set exhausted after {expansions} expansions")

    def _heuristic(self, yaws: list[float], goal: tuple[float, float, float]):
        """Distance to the goal + the turns any path must still make, times `heuristic_weight`.

        The turn term is a lower bound: a path that turns at most j times only moves inside the cone of
        headings within +- j * 30 deg of the current one, so the goal's tolerance ball must touch that cone.
        """
        gx, gy, gz = goal
        tol, w, penalty = self.cfg.goal_tolerance_m, self.cfg.heuristic_weight, self.cfg.turn_penalty
        turn_rad, two_pi = math.radians(C.TURN_DEGREES), 2.0 * math.pi

        def heuristic(x: float, y: float, z: float, h: int) -> float:
            dx, dy = gx - x, gy - y
            horizontal = math.hypot(dx, dy)
            turns = 0
            if horizontal > tol:
                delta = abs((math.atan2(dy, dx) - yaws[h] + math.pi) % two_pi - math.pi)  # [0, pi]
                turns = max(0, math.ceil((delta - math.asin(tol / horizontal)) / turn_rad - 1e-9))
            return w * (math.hypot(horizontal, gz - z) + penalty * turns)

        return heuristic

    @staticmethod
    def _result(node, xs, ys, zs, hs, parents, moves, expansions, cost) -> PlanResult:
        chain = []
        while node != -1:
            chain.append(node)
            node = parents[node]
        chain.reverse()
        primitives: list[int] = []
        for prev, cur in zip(chain[:-1], chain[1:]):
            move = moves[cur]
            if move == _UP:
                primitives.append(C.ACTION_ASCEND)
            elif move == _DOWN:
                primitives.append(C.ACTION_DESCEND)
            else:
                turns = turns_between(hs[prev], move)
                primitives += [C.ACTION_TURN_LEFT if turns > 0 else C.ACTION_TURN_RIGHT] * abs(turns)
                primitives.append(C.ACTION_FORWARD)
        positions = np.array([[xs[i], ys[i], zs[i]] for i in chain], dtype=np.float64)
        return PlanResult(primitives, positions, hs[chain[-1]], expansions, cost)

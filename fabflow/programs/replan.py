"""Collision re-planning of a work package's program: routes around what is built.

:func:`checked_program` compiles a work package (:mod:`fabflow.programs.assemble`),
checks it for collisions (:mod:`fabflow.programs.collision`) and re-plans the
blocks whose moves collide or swing widely with the routes of
:class:`~fabflow.programs.motions.Route` (see :func:`replanned_program`); what
still collides is an error, or with ``program.check_collisions: report`` is
written into the program (:func:`with_contacts`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError
from fabflow.programs.assemble import compile_program
from fabflow.programs.chain_memo import ChainMemo
from fabflow.programs.collision import Contact, check_package
from fabflow.programs.collision_model import (
    Obstacles,
    environment,
    placements,
    safe_heights,
    tuck_heights,
)
from fabflow.programs.collision_motion import CheckMemo
from fabflow.programs.ir import Program
from fabflow.programs.motions import Placement, Route, work_package_motion
from fabflow.project import Project
from fabflow.tasks.targets import T_base_pick_tool

SAFE_WIDTH = 0.5
"""Plan distance from the line magazine - place within which the structure sets the
safe height of a re-planned block (metres): the arm's forearm and wrist pass there."""

CompileMemo = dict[tuple[tuple[str, int], ...], tuple[Program, dict[str, int]] | None]
"""A package's compiled programs by the route levels asked for (sorted ``(id, level)``):
the program and the levels it used, None where no program was found."""


def with_contacts(program: Program, contacts: Sequence[Contact], clearance: float) -> Program:
    """The program with its remaining collisions in its checks (``collision_moves``) and,
    where there are any, in its header (how many moves, the worst) and as a stop the
    operator must confirm before the first motion (``Program.confirm``)."""
    moves = len({c.move for c in contacts})
    checks = {**program.checks, "collision_moves": moves}
    if not contacts:
        return dataclasses.replace(program, checks=checks)
    worst = min(contacts, key=lambda c: c.distance)
    header = {
        **program.header,
        "collisions": (
            f"{moves} moves closer than {clearance * 1000:g} mm to an obstacle after "
            f"re-planning; the worst: {worst.describe()}. Do not run them as they are."
        ),
    }
    stop = f"{moves} move{'s' if moves != 1 else ''} may collide, see the header"
    return dataclasses.replace(
        program, header=header, checks=checks, confirm=(*program.confirm, stop)
    )


def checked_program(
    name: str,
    elements: Sequence[Element],
    built: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
    coming: Sequence[tuple[Element, int]] = (),
    **options: Any,
) -> Program:
    """Compile a work package and check it for collisions; re-plan what collides.

    :func:`replanned_program` (the parameters are its); a collision that remains
    is an :class:`InfeasibleError` naming the element, the move, the body and
    the penetration.
    """
    program, contacts = replanned_program(
        name, elements, built, project, T_world_base, header, coming=coming, **options
    )
    if contacts:
        worst = min(contacts, key=lambda c: c.distance)
        raise InfeasibleError(
            f"program {name}: {len(contacts)} collision(s) at "
            f"{project.program.clearance * 1000:g} mm clearance; the worst: {worst.describe()}"
        )
    return program


def replanned_program(
    name: str,
    elements: Sequence[Element],
    built: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
    coming: Sequence[tuple[Element, int]] = (),
    **options: Any,
) -> tuple[Program, list[Contact]]:
    """A work package's program, re-planned around its collisions, and what remains.

    Parameters
    ----------
    name
        Program name.
    elements
        The package's elements in build order.
    built
        Elements standing when it starts; ``coming``: the hand-built ones that
        come during it (:func:`fabflow.design.elements.structure_timeline`).
    project
        Robot, platform, site obstacles and ``program`` settings (the clearance).
    T_world_base
        The station's localized base pose.
    header
        Header comments of the program.
    options
        To :func:`fabflow.programs.assemble.compile_program` (lift, payloads, beads).

    Returns
    -------
    program, contacts
        The program and the contacts still closer than the clearance (empty
        when it is collision-free).

    Placement first (:func:`fabflow.programs.collision_model.placements`), then
    re-planning in rounds: every block with a contact or a wide swing (and
    the block before one whose move to the magazine or HOME has one) takes the
    next of its candidate routes (:func:`candidate_routes`); a route the arm
    cannot follow is passed over. It stops when none is left, when every such
    block has tried all its routes, or after :data:`REPLAN_ROUNDS` rounds. Then
    each block takes the route on which its own moves fared best (fewest
    contacts, then linear moves through A5 = 0, then wide swings), and of that
    program and those of the rounds the best by the same order is returned.
    """
    obstacles = environment(project, T_world_base, built, elements, coming)
    memo: CheckMemo = {}  # the rounds' programs share most moves: each is checked once
    programs: CompileMemo = {}  # and the rounds and the final choice often compile one twice
    placed = placements(obstacles, elements, project)
    steps = work_package_motion(elements, project, T_world_base, placements=placed)
    chains: ChainMemo = {}  # and most of their chains are solved once
    program = compile_program(name, steps, project, T_world_base, header, memo=chains, **options)
    contacts = check_package(program, project, obstacles, elements, memo=memo)
    if not contacts and not _swings(program):
        return program, contacts
    candidates = candidate_routes(elements, project, T_world_base, obstacles)
    index = {e.id: j for j, e in enumerate(elements)}
    level: dict[str, int] = {}
    defects = _defects(program, contacts)
    tried = {e: {-1: d} for e, d in defects.items() if e in candidates}
    best = (_total(program, contacts), program, contacts)

    def compile_routes(levels: dict[str, int]) -> tuple[Program, dict[str, int]] | None:
        return _compile_routes(
            name, elements, project, T_world_base, header, candidates, levels, placed, options,
            programs, chains,
        )  # fmt: skip

    for _ in range(REPLAN_ROUNDS):
        # a route's own linear moves through A5 = 0 send its block on to the next route
        routed = [c for c in _flips(program) if _owner(program, c) in level]
        faults = [*contacts, *_swings(program), *routed]
        hit = {_owner(program, c) for c in faults} & set(candidates)
        hit |= {
            elements[index[c.element] - 1].id
            for c in faults
            if c.element in index and index[c.element] > 0 and c.label in _TO_MAGAZINE
        } & set(candidates)
        trial = dict(level)
        for eid in hit:  # the next route; len(candidates): out of routes, none
            k = level.get(eid, -1) + 1
            routes = candidates[eid]
            # the joint-descent twin of a route only for its linear moves through A5 = 0
            if k < len(routes) and routes[k].joint_descent and sum(defects.get(eid, (0,))[::2]):
                k += 1
            trial[eid] = min(k, len(routes))
        if trial == level:
            break
        compiled = compile_routes(trial)
        if compiled is None:
            break
        program, level = compiled
        contacts = check_package(program, project, obstacles, elements, memo=memo)
        best = min(best, (_total(program, contacts), program, contacts), key=lambda b: b[0])
        defects = _defects(program, contacts)
        for eid, d in defects.items():
            if eid in candidates and level.get(eid, -1) < len(candidates[eid]):
                tried[eid].setdefault(level.get(eid, -1), d)
    # each block on the route where its own moves fared best, checked as a whole
    choice = {e: min(t, key=lambda k: (t[k], k)) for e, t in tried.items()}
    choice = {e: k for e, k in choice.items() if k >= 0}
    compiled = compile_routes(choice)
    if compiled is not None:
        program = compiled[0]
        contacts = check_package(program, project, obstacles, elements, memo=memo)
        best = min(best, (_total(program, contacts), program, contacts), key=lambda b: b[0])
    return best[1], best[2]


def _swings(program: Program) -> list[Contact]:
    """The program's wide swings (``Program.checks["swing_moves"]``), as contacts of
    distance 0 with nothing, for the re-planning."""
    return _as_contacts(program, program.checks.get("swing_moves", []), "arm", "swing")


def _flips(program: Program) -> list[Contact]:
    """The program's linear moves whose configuration changes, A5 through 0 (a change
    the controller refuses; ``Program.checks["inside_lin_moves"]``), as contacts for
    the re-planning."""
    return _as_contacts(program, program.checks.get("inside_lin_moves", []), "wrist", "A5 = 0")


def _as_contacts(program: Program, which: Sequence[int], body: str, what: str) -> list[Contact]:
    moves = program.moves
    return [Contact(k, moves[k].element, moves[k].label, body, what, 0.0) for k in which]


def _defects(program: Program, contacts: list[Contact]) -> dict[str | None, tuple[int, ...]]:
    """Per element (HOME moves count for the one before): the moves with a contact, the
    linear moves through A5 = 0 and the wide swings, in that order of weight."""
    counts: dict[str | None, list[int]] = {m.element: [0, 0, 0] for m in program.moves}
    for kind, faults in enumerate((contacts, _flips(program), _swings(program))):
        for move in {c.move: c for c in faults}.values():
            counts.setdefault(_owner(program, move), [0, 0, 0])[kind] += 1
    return {e: tuple(c) for e, c in counts.items()}


def _total(program: Program, contacts: list[Contact]) -> tuple[int, int, int]:
    """A program's contact moves, linear moves through A5 = 0 and wide swings."""
    return (len({c.move for c in contacts}), len(_flips(program)), len(_swings(program)))


def _owner(program: Program, contact: Contact) -> str | None:
    """The element a contact is re-planned with: its move's, or for a HOME move the
    element before it (ending tucked, the swing home starts tucked)."""
    if contact.element is not None:
        return contact.element
    moves = program.moves
    return next((m.element for m in reversed(moves[: contact.move]) if m.element is not None), None)


REPLAN_ROUNDS = 10
"""Rounds of re-planning a work package's colliding blocks."""
_TO_MAGAZINE = ("pick approach", "over magazine")
"""Labels of the joint move from the previous block's place back to the magazine."""
TUCK_FRACTIONS = (1.0, 0.8, 0.6)
"""Tuck radii of the candidate routes, as fractions of the magazine's radius about A1."""
MIN_TUCK_RADIUS = 0.3
"""The smallest tuck radius about A1 (metres)."""


def candidate_routes(
    elements: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    obstacles: Obstacles,
) -> dict[str, list[Route]]:
    """The routes a colliding block tries, in order, per block of a work package.

    First straight over the structure between the magazine and its place
    (:func:`fabflow.programs.collision_model.safe_heights`), where the structure
    is in the way; then tucked (:class:`~fabflow.programs.motions.Route`) at
    :data:`TUCK_FRACTIONS` of the magazine's radius about A1, first at the
    higher of the two approach heights, then above all the structure the tucked
    arm could sweep (:func:`fabflow.programs.collision_model.tuck_heights`).
    Each route is followed by its twin with joint moves down to the place
    approach and back up, tried only where the route's own linear moves take A5
    through 0.
    """
    T_world_base = np.asarray(T_world_base, dtype=float)
    T_base_pick = T_base_pick_tool(project)
    radius = float(np.hypot(*T_base_pick[:2, 3]))
    heights = safe_heights(
        obstacles, elements, T_world_base @ T_base_pick, project.program.clearance, SAFE_WIDTH
    )
    clearance = project.program.clearance
    # no tuck near the A1 axis, where the wrist nears the shoulder singularity
    fractions = [f for f in TUCK_FRACTIONS if f * radius >= MIN_TUCK_RADIUS]
    above = [tuck_heights(obstacles, elements, T_world_base, f * radius, clearance)
             for f in fractions]  # fmt: skip
    out = {}
    for e in elements:
        if e.type != "block":
            continue
        routes = [Route(height=heights[e.id])] if e.id in heights else []
        routes += [Route(tuck=f * radius) for f in fractions]
        routes += [
            Route(height=h[e.id], tuck=f * radius)
            for f, h in zip(fractions, above, strict=True)
            if e.id in h
        ]
        out[e.id] = [
            r for route in routes for r in (route, dataclasses.replace(route, joint_descent=True))
        ]
    return out


def _compile_routes(
    name: str,
    elements: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
    candidates: dict[str, list[Route]],
    level: dict[str, int],
    placed: dict[str, Placement],
    options: dict[str, Any],
    memo: CompileMemo,
    chains: ChainMemo,
) -> tuple[Program, dict[str, int]] | None:
    """Compile with each block's route ``candidates[id][level[id]]`` (none where the level
    is past its routes); a block whose route the arm cannot follow moves on to its next.

    Returns the program and the levels used, or None when an infeasible target
    belongs to no re-planned block. ``memo`` holds the outcome of every set of
    levels tried before for this package (the rounds and the final choice often
    ask for the same one again): compiling is deterministic, so it is reused; ``chains``
    the chains solved so far (:mod:`fabflow.programs.chain_memo`)."""
    level = dict(level)
    tried: list[tuple[tuple[str, int], ...]] = []
    outcome: tuple[Program, dict[str, int]] | None = None
    while True:  # each pass moves one block on: at most sum(len(c)) passes
        key = tuple(sorted(level.items()))
        if key in memo:
            outcome = memo[key]
            break
        tried.append(key)
        routes = {e: candidates[e][k] for e, k in level.items() if k < len(candidates[e])}
        steps = work_package_motion(elements, project, T_world_base, routes, placed)
        try:
            program = compile_program(
                name, steps, project, T_world_base, header, memo=chains, **options
            )
        except InfeasibleError as error:
            if error.element not in routes:
                break
            level[error.element] += 1
            continue
        outcome = program, level
        break
    for key in tried:  # each of them leads to this outcome
        memo[key] = outcome
    return None if outcome is None else (outcome[0], dict(outcome[1]))

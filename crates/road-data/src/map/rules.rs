//! A map's priority rules: Lanelet2's `right_of_way` and `all_way_stop` regulatory elements,
//! by lanelet index. A vehicle on a `yield` lanelet gives way at the lanelet's end (its stop
//! line): to traffic on the `right_of_way` lanelets, or, at an all-way stop, to everyone who
//! stopped at the element's lines before it and to anyone in its way through the junction.
//!
//! The conflicts inside a junction (which of the lanelets leaving the yield lanelets cross or
//! merge) are found from the geometry once, when the map is read: a lanelet conflicts with
//! another when a point of its centre line lies inside the other (a crossing or a merge);
//! two lanelets that only share a bound (neighbours) do not.

use serde::{Deserialize, Serialize};

use super::Lanelet;

/// Which rule a [`PriorityRule`] element states.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RuleKind {
    /// `right_of_way`: the yield lanelets give way to traffic on the priority lanelets.
    Yield,
    /// `all_way_stop`: every approach stops at its line, then goes in the order of arrival.
    AllWayStop,
}

/// One regulatory element of a map, by lanelet index into [`crate::LaneletMap::lanelets`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PriorityRule {
    /// OSM relation id.
    pub id: i64,
    pub kind: RuleKind,
    /// Lanelets whose traffic gives way at their end.
    pub yield_lanelets: Vec<u32>,
    /// Lanelets whose traffic has the way (empty at an all-way stop).
    pub priority_lanelets: Vec<u32>,
    /// The lanelets that leave the yield lanelets (the junction), each with the junction's
    /// lanelets it conflicts with (crosses or merges into), both by lanelet index.
    pub junction: Vec<(u32, Vec<u32>)>,
}

impl PriorityRule {
    /// A rule over `lanelets` (a map's, topology linked), its junction found from them.
    pub fn new(
        lanelets: &[Lanelet],
        id: i64,
        kind: RuleKind,
        yield_lanelets: Vec<u32>,
        priority_lanelets: Vec<u32>,
    ) -> Self {
        let junction = junction_of(lanelets, &yield_lanelets);
        Self {
            id,
            kind,
            yield_lanelets,
            priority_lanelets,
            junction,
        }
    }

    /// The junction's lanelets that `lanelet` conflicts with (none when it is not one of them).
    pub fn conflicts_of(&self, lanelet: u32) -> &[u32] {
        self.junction
            .iter()
            .find(|(l, _)| *l == lanelet)
            .map_or(&[], |(_, c)| c.as_slice())
    }

    /// Whether the element names `lanelet` as one that gives way.
    pub fn yields_on(&self, lanelet: u32) -> bool {
        self.yield_lanelets.contains(&lanelet)
    }
}

/// Whether a point of `a`'s centre line lies inside `b`, or one of `b`'s inside `a`: they cross
/// or merge. The centre lines' first and last metre are left out: lanelets that leave the same
/// lanelet, or run into the same one, touch there without being in each other's way.
fn lanelets_conflict(a: &Lanelet, b: &Lanelet) -> bool {
    let inner = |l: &Lanelet| {
        let n = l.centre_m.len();
        // Centre points lie about a metre apart (`map::CENTRE_SPACING_M`).
        l.centre_m
            .iter()
            .skip(1)
            .take(n.saturating_sub(2))
            .copied()
            .collect::<Vec<_>>()
    };
    a.bounds.overlaps(&b.bounds)
        && (inner(a).into_iter().any(|p| b.contains(p))
            || inner(b).into_iter().any(|p| a.contains(p)))
}

/// How many lanelets deep a junction reaches past its yield lanelets' successors.
const JUNCTION_DEPTH: usize = 3;

/// The junction of an element: every successor of its yield lanelets, and their successors
/// that still conflict with one of those (a box two lanelets deep), each with the junction's
/// lanelets it conflicts with.
fn junction_of(lanelets: &[Lanelet], yield_lanelets: &[u32]) -> Vec<(u32, Vec<u32>)> {
    let conflict = |a: u32, b: u32| lanelets_conflict(&lanelets[a as usize], &lanelets[b as usize]);
    let mut junction: Vec<u32> = yield_lanelets
        .iter()
        .flat_map(|&y| lanelets[y as usize].successors.iter().copied())
        .collect();
    junction.sort_unstable();
    junction.dedup();
    let mut frontier = junction.clone();
    for _ in 0..JUNCTION_DEPTH {
        let mut next = Vec::new();
        for &l in &frontier {
            for &s in &lanelets[l as usize].successors {
                let in_box = junction.iter().any(|&m| m != l && conflict(s, m));
                if in_box && !junction.contains(&s) && !next.contains(&s) {
                    next.push(s);
                }
            }
        }
        junction.extend(&next);
        frontier = next;
    }
    junction.sort_unstable();
    junction
        .iter()
        .map(|&l| {
            let conflicts = junction
                .iter()
                .copied()
                .filter(|&m| m != l && conflict(l, m))
                .collect();
            (l, conflicts)
        })
        .collect()
}

//! Scenes built from code, every byte of them redistributable (no INTERACTION data): a
//! four-arm, single-lane roundabout with counter-clockwise (right-hand) traffic, a four-way
//! intersection and a motorway-style merge ([`ProceduralMap`]), each with vehicles whose 1 s
//! histories are generated along routes through it. `road demo` simulates them closed loop
//! with a scripted ego; `road serve` offers them as `map.procedural`.

use std::f64::consts::FRAC_PI_2;

use glam::{DMat2, DVec2};
use road_data::geometry::{Aabb, Point, dist, hypot_length, resample};
use road_data::map::{Lanelet, MapSkips};
use road_data::rules::{PriorityRule, RuleKind};
use road_data::{AgentType, LaneletMap, SceneFrame, SceneWindow, WindowConfig};

use crate::closed_loop::ExternalDriver;
use crate::{Error, Pose, Result};

/// Seconds per simulated step (INTERACTION's 10 Hz), re-exported for the procedural scenes'
/// users.
pub use road_data::tracks::STEP_SECS;

/// Ring centre-line radius.
const RING_RADIUS_M: f64 = 20.0;
const RING_WIDTH_M: f64 = 5.0;
const LANE_WIDTH_M: f64 = 3.75;
/// Arms start this far outside the ring's centre line and run `ARM_LENGTH_M`.
const ARM_GAP_M: f64 = 9.0;
const ARM_LENGTH_M: f64 = 60.0;
/// Where connectors meet the ring, either side of an arm's axis.
const MERGE_ANGLE_RAD: f64 = 0.45;

pub use crate::route::Route;

/// The scripted ego of the demo: it drives its route at a constant speed, whatever the NPCs
/// do (an ego stack that does not yield, so that the NPCs have to).
#[derive(Debug, Clone)]
pub struct ScriptedEgo {
    pub scene: usize,
    pub agent: usize,
    pub route: Route,
    /// Arc length at the last observed step.
    pub start_m: f64,
    pub speed_mps: f64,
}

impl ExternalDriver for ScriptedEgo {
    fn pose(&mut self, scene: usize, agent: usize, tick: usize, _world: &[Pose]) -> Result<Pose> {
        if (scene, agent) != (self.scene, self.agent) {
            return Err(Error::External {
                scene,
                agent,
                reason: format!(
                    "the scripted ego drives scene {} agent {} only",
                    self.scene, self.agent
                ),
            });
        }
        Ok(self
            .route
            .pose_at(self.start_m + self.speed_mps * STEP_SECS * (tick + 1) as f64))
    }
}

/// The demo scene: its map, a window holding the vehicles' 1 s histories, and the ego.
#[derive(Debug, Clone)]
pub struct ProceduralScene {
    pub map: LaneletMap,
    pub window: SceneWindow,
    /// Every vehicle's route (the ego follows its own; the others are the model's).
    pub routes: Vec<Route>,
    pub ego: ScriptedEgo,
}

fn lanelet(id: i64, subtype: &str, centre: Vec<Point>, width_m: f64) -> Lanelet {
    let n = centre.len();
    let mut left = Vec::with_capacity(n);
    let mut right = Vec::with_capacity(n);
    for i in 0..n {
        let (a, b) = (centre[i.saturating_sub(1)], centre[(i + 1).min(n - 1)]);
        let len = dist(a, b).max(1e-9);
        // Left normal of the driving direction.
        let normal = ((DVec2::from(b) - DVec2::from(a)) / len).perp();
        let half_width = normal * (0.5 * width_m);
        left.push((DVec2::from(centre[i]) + half_width).into());
        right.push((DVec2::from(centre[i]) - half_width).into());
    }
    let bounds = Aabb::of(&left.iter().chain(&right).copied().collect::<Vec<_>>());
    Lanelet {
        id,
        subtype: Some(subtype.to_owned()),
        left_way: 2 * id,
        right_way: 2 * id + 1,
        left_m: left,
        right_m: right,
        centre_m: centre,
        successors: Vec::new(),
        neighbours: Vec::new(),
        bounds,
    }
}

/// Consecutive lanelets share their bound points, as a Lanelet2 map's share nodes: each
/// lanelet's first bound points become those of a predecessor whose last ones lie within
/// [`SHARED_BOUND_TOLERANCE_M`] of them (of several, the one that runs on into it most nearly
/// straight; a merge from a lane of another width keeps its own). Built separately, a curve's last chord and a straight's start
/// left wedge-shaped cracks between them, and a vehicle standing in one was held at the
/// "road's edge" for good (issue 39).
fn with_shared_bounds(mut lanelets: Vec<Lanelet>) -> Vec<Lanelet> {
    let direction = |a: Point, b: Point| (DVec2::from(b) - DVec2::from(a)).normalize_or_zero();
    for s in 0..lanelets.len() {
        let next = &lanelets[s];
        let ([first, second, ..], Some(&next_left), Some(&next_right)) = (
            &next.centre_m[..],
            next.left_m.first(),
            next.right_m.first(),
        ) else {
            continue;
        };
        let start_direction = direction(*first, *second);
        let best = (0..lanelets.len())
            .filter(|&p| lanelets[p].successors.contains(&(s as u32)))
            .filter_map(|p| {
                let l = &lanelets[p];
                let ([.., before, end], Some(&left), Some(&right)) =
                    (&l.centre_m[..], l.left_m.last(), l.right_m.last())
                else {
                    return None;
                };
                let joins = dist(next_left, left) <= SHARED_BOUND_TOLERANCE_M
                    && dist(next_right, right) <= SHARED_BOUND_TOLERANCE_M;
                joins.then(|| (left, right, direction(*before, *end).dot(start_direction)))
            })
            .max_by(|a, b| a.2.total_cmp(&b.2));
        if let Some((left, right, _)) = best {
            let next = &mut lanelets[s];
            next.left_m[0] = left;
            next.right_m[0] = right;
            next.bounds = Aabb::of(
                &next
                    .left_m
                    .iter()
                    .chain(&next.right_m)
                    .copied()
                    .collect::<Vec<_>>(),
            );
        }
    }
    lanelets
}

/// How far apart a lanelet's start and its predecessor's end bound points may lie and still be
/// joined into one ([`with_shared_bounds`]), metres.
const SHARED_BOUND_TOLERANCE_M: f64 = 0.5;

/// The unit vector at `angle` (counter-clockwise from +x) and the one to its left.
fn axes(angle: f64) -> (DVec2, DVec2) {
    let axis = DVec2::from_angle(angle);
    (axis, axis.perp())
}

fn polar(r: f64, angle: f64) -> DVec2 {
    DVec2::from_angle(angle) * r
}

fn arc(r: f64, from: f64, to: f64) -> Vec<Point> {
    let steps = (((to - from) * r).abs().ceil() as usize).max(2);
    (0..=steps)
        .map(|i| polar(r, from + (to - from) * i as f64 / steps as f64).into())
        .collect()
}

/// The cubic Bézier curve of control points `p` at `count + 1` evenly spaced parameters.
fn bezier(p: [DVec2; 4], count: usize) -> Vec<Point> {
    (0..=count)
        .map(|i| {
            let t = i as f64 / count as f64;
            let u = 1.0 - t;
            let w = [u * u * u, 3.0 * u * u * t, 3.0 * u * t * t, t * t * t];
            (p[0] * w[0] + p[1] * w[1] + p[2] * w[2] + p[3] * w[3]).into()
        })
        .collect()
}

fn line(a: DVec2, b: DVec2) -> Vec<Point> {
    let steps = (hypot_length(b - a).ceil() as usize).max(2);
    (0..=steps)
        .map(|i| a.lerp_monotonic(b, i as f64 / steps as f64).into())
        .collect()
}

/// Pushes the lane along `centre` as consecutive lanelets (ids `id`, `id + 1`, …) of at most
/// about `piece_m` each, successors linked, as lane maps cut long roads (and as the
/// INTERACTION maps the model learnt from do). Returns their indices in driving order.
fn chain(lanelets: &mut Vec<Lanelet>, id: i64, centre: &[Point], piece_m: f64) -> Vec<usize> {
    let length: f64 = centre.windows(2).map(|p| dist(p[0], p[1])).sum();
    let pieces = ((length / piece_m).ceil() as usize).max(1);
    let mut cuts = vec![0usize];
    let mut walked = 0.0;
    for i in 1..centre.len() {
        walked += dist(centre[i - 1], centre[i]);
        if walked >= length * cuts.len() as f64 / pieces as f64 - 1e-9 && i < centre.len() - 1 {
            cuts.push(i);
        }
    }
    cuts.push(centre.len() - 1);
    cuts.dedup();
    let mut indices = Vec::with_capacity(cuts.len() - 1);
    for (k, pair) in cuts.windows(2).enumerate() {
        indices.push(lanelets.len());
        lanelets.push(lanelet(
            id + k as i64,
            "road",
            centre[pair[0]..=pair[1]].to_vec(),
            LANE_WIDTH_M,
        ));
    }
    for pair in indices.windows(2) {
        lanelets[pair[0]].successors.push(pair[1] as u32);
    }
    indices
}

/// Lanelet indices of the roundabout, by role.
struct Layout {
    map: LaneletMap,
    /// Per arm: inbound lane, entry connector, exit connector, outbound lane.
    inbound: [usize; 4],
    entry: [usize; 4],
    exit: [usize; 4],
    outbound: [usize; 4],
    /// Ring arcs in counter-clockwise order; arc `2k` runs from arm k's entry to arm k+1's
    /// exit, arc `2k + 1` from arm k+1's exit to its entry.
    ring: [usize; 8],
}

fn roundabout_map() -> Layout {
    let mut lanelets = Vec::new();
    let mut push = |l: Lanelet| {
        lanelets.push(l);
        lanelets.len() - 1
    };
    let (mut inbound, mut entry, mut exit, mut outbound) = ([0; 4], [0; 4], [0; 4], [0; 4]);
    let mut ring = [0; 8];
    let r = RING_RADIUS_M;
    let tangent = |angle: f64| axes(angle).1; // counter-clockwise
    for k in 0..4 {
        let theta = k as f64 * FRAC_PI_2;
        let (axis, ccw_side) = axes(theta);
        let offset = 0.5 * LANE_WIDTH_M + 0.25;
        let at = |d: f64, side: f64| axis * d + ccw_side * (side * offset);
        let (near, far) = (r + ARM_GAP_M, r + ARM_GAP_M + ARM_LENGTH_M);
        let id = 1000 + 10 * k as i64;
        inbound[k] = push(lanelet(
            id,
            "road",
            line(at(far, 1.0), at(near, 1.0)),
            LANE_WIDTH_M,
        ));
        let merge = theta + MERGE_ANGLE_RAD;
        let p3 = polar(r, merge);
        let t3 = tangent(merge);
        entry[k] = push(lanelet(
            id + 1,
            "road",
            bezier(
                [at(near, 1.0), at(near, 1.0) - axis * 4.0, p3 - t3 * 4.0, p3],
                16,
            ),
            LANE_WIDTH_M,
        ));
        let diverge = theta - MERGE_ANGLE_RAD;
        let p0 = polar(r, diverge);
        let t0 = tangent(diverge);
        exit[k] = push(lanelet(
            id + 2,
            "road",
            bezier(
                [
                    p0,
                    p0 + t0 * 4.0,
                    at(near, -1.0) - axis * 4.0,
                    at(near, -1.0),
                ],
                16,
            ),
            LANE_WIDTH_M,
        ));
        outbound[k] = push(lanelet(
            id + 3,
            "road",
            line(at(near, -1.0), at(far, -1.0)),
            LANE_WIDTH_M,
        ));
    }
    for k in 0..4 {
        let theta = k as f64 * FRAC_PI_2;
        let next = theta + FRAC_PI_2;
        let id = 2000 + 10 * k as i64;
        ring[2 * k] = push(lanelet(
            id,
            "road",
            arc(r, theta + MERGE_ANGLE_RAD, next - MERGE_ANGLE_RAD),
            RING_WIDTH_M,
        ));
        ring[2 * k + 1] = push(lanelet(
            id + 1,
            "road",
            arc(r, next - MERGE_ANGLE_RAD, next + MERGE_ANGLE_RAD),
            RING_WIDTH_M,
        ));
    }
    // Topology: inbound → entry → ring; ring → ring; ring → exit → outbound.
    for k in 0..4 {
        lanelets[inbound[k]].successors.push(entry[k] as u32);
        lanelets[entry[k]].successors.push(ring[2 * k] as u32);
        lanelets[exit[k]].successors.push(outbound[k] as u32);
        lanelets[ring[2 * k]]
            .successors
            .push(ring[2 * k + 1] as u32);
        lanelets[ring[2 * k + 1]]
            .successors
            .push(ring[(2 * k + 2) % 8] as u32);
        lanelets[ring[2 * k]]
            .successors
            .push(exit[(k + 1) % 4] as u32);
    }
    let lanelets = with_shared_bounds(lanelets);
    // Entering traffic gives way to the ring's, as at the INTERACTION roundabouts (their
    // `right_of_way` elements): each entry yields to the arc that runs past it.
    let priority_rules = (0..4)
        .map(|k| {
            PriorityRule::new(
                &lanelets,
                5000 + k as i64,
                RuleKind::Yield,
                vec![entry[k] as u32],
                vec![ring[(2 * k + 7) % 8] as u32],
            )
        })
        .collect();
    Layout {
        map: LaneletMap {
            location: "procedural_roundabout".into(),
            lanelets,
            skipped: MapSkips::default(),
            priority_rules,
        },
        inbound,
        entry,
        exit,
        outbound,
        ring,
    }
}

impl Layout {
    /// The centre line from arm `from`'s inbound lane around to arm `to`'s outbound lane.
    fn route(&self, from: usize, to: usize) -> Route {
        let l = &self.map.lanelets;
        let mut points: Vec<Point> = Vec::new();
        points.extend(&l[self.inbound[from]].centre_m);
        points.extend(&l[self.entry[from]].centre_m);
        let mut k = from;
        loop {
            points.extend(&l[self.ring[2 * k]].centre_m);
            if (k + 1) % 4 == to {
                break;
            }
            points.extend(&l[self.ring[2 * k + 1]].centre_m);
            k = (k + 1) % 4;
        }
        points.extend(&l[self.exit[to]].centre_m);
        points.extend(&l[self.outbound[to]].centre_m);
        Route::new(points)
    }
}

/// The procedural maps, by name (`road demo --map`, `map.procedural` of `road serve`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProceduralMap {
    /// Four arms, one lane each way, a single-lane ring: seven vehicles.
    Roundabout,
    /// A four-way crossing of two roads, one lane each way, with a connector for every
    /// movement (a signalised junction's geometry; no signals are simulated): six vehicles.
    Intersection,
    /// A one-lane main road joined by a one-lane on-ramp: six vehicles.
    Merge,
}

impl ProceduralMap {
    pub const ALL: [Self; 3] = [Self::Roundabout, Self::Intersection, Self::Merge];

    pub fn name(self) -> &'static str {
        match self {
            Self::Roundabout => "roundabout",
            Self::Intersection => "intersection",
            Self::Merge => "merge",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }

    /// Every name, comma-separated (for error messages and help).
    pub fn names() -> String {
        Self::ALL.map(Self::name).join(", ")
    }
}

/// A vehicle of a procedural scene: its route, where it is at the last observed step and its
/// constant speed over the history.
#[derive(Debug, Clone, Copy)]
struct Vehicle {
    route: usize,
    start_m: f64,
    speed_mps: f64,
    length_m: f32,
    width_m: f32,
}

/// The demo roundabout with seven vehicles (the ego is agent 0) and 1 s of history each,
/// windowed like INTERACTION data with `config` (`observed_steps` history steps).
pub fn roundabout(config: &WindowConfig, observed_steps: usize) -> Result<ProceduralScene> {
    procedural(ProceduralMap::Roundabout, config, observed_steps)
}

/// A procedural scene (the ego is agent 0, on its route at a constant speed), windowed like
/// INTERACTION data with `config` (`observed_steps` history steps).
pub fn procedural(
    kind: ProceduralMap,
    config: &WindowConfig,
    observed_steps: usize,
) -> Result<ProceduralScene> {
    procedural_turned(kind, config, observed_steps, 0.0)
}

/// [`procedural`] with the whole scene (map, routes, vehicles) turned by `rotation_rad`
/// (counter-clockwise) about the map's origin: the same traffic at another orientation. A
/// model that reads the lanes drives it the same way; one that learnt each INTERACTION map's
/// fixed orientation does not (`road demo --rotate-deg`).
pub fn procedural_turned(
    kind: ProceduralMap,
    config: &WindowConfig,
    observed_steps: usize,
    rotation_rad: f64,
) -> Result<ProceduralScene> {
    if observed_steps < 2 {
        return Err(Error::Config(format!(
            "the procedural scene needs at least 2 observed steps, got {observed_steps}"
        )));
    }
    let (map, routes, vehicles) = match kind {
        ProceduralMap::Roundabout => roundabout_scene(),
        ProceduralMap::Intersection => intersection_scene(),
        ProceduralMap::Merge => merge_scene(),
    };
    let (map, routes) = if rotation_rad == 0.0 {
        (map, routes)
    } else {
        turned(map, routes, rotation_rad)
    };
    scene_of(map, routes, &vehicles, config, observed_steps)
}

/// `map` and `routes` turned by `rotation_rad` about the origin (bounds recomputed; topology
/// and ids unchanged).
fn turned(mut map: LaneletMap, routes: Vec<Route>, rotation_rad: f64) -> (LaneletMap, Vec<Route>) {
    let turn = DMat2::from_angle(rotation_rad);
    let turn_all = |points: &mut Vec<Point>| {
        for p in points.iter_mut() {
            *p = (turn * DVec2::from(*p)).into();
        }
    };
    for lanelet in &mut map.lanelets {
        turn_all(&mut lanelet.left_m);
        turn_all(&mut lanelet.right_m);
        turn_all(&mut lanelet.centre_m);
        let outline: Vec<Point> = lanelet
            .left_m
            .iter()
            .chain(&lanelet.right_m)
            .copied()
            .collect();
        lanelet.bounds = Aabb::of(&outline);
    }
    let routes = routes
        .into_iter()
        .map(|route| {
            let mut points = route.into_points();
            turn_all(&mut points);
            Route::new(points)
        })
        .collect();
    (map, routes)
}

fn roundabout_scene() -> (LaneletMap, Vec<Route>, Vec<Vehicle>) {
    let layout = roundabout_map();
    let inbound_len = dist(
        layout.map.lanelets[layout.inbound[0]].centre_m[0],
        *layout.map.lanelets[layout.inbound[0]]
            .centre_m
            .last()
            .expect("lanes have points"),
    );
    // (from arm, to arm, arc length at the last observed step, speed): the ego enters from the
    // south and leaves east; others circulate, queue and approach.
    let trips: [(usize, usize, f64, f64, f32, f32); 7] = [
        (3, 0, inbound_len - 14.0, 7.0, 4.6, 1.9),
        (0, 2, inbound_len + 14.0, 6.0, 4.4, 1.8),
        (2, 3, inbound_len + 30.0, 6.5, 4.8, 1.9),
        (1, 3, inbound_len - 25.0, 8.0, 4.2, 1.8),
        (2, 1, inbound_len - 8.0, 5.0, 4.5, 1.9),
        (0, 3, inbound_len - 30.0, 7.5, 5.0, 2.0),
        (1, 0, inbound_len + 40.0, 6.5, 4.3, 1.8),
    ];
    let routes = trips
        .iter()
        .map(|&(from, to, ..)| layout.route(from, to))
        .collect();
    let vehicles = trips
        .iter()
        .enumerate()
        .map(
            |(i, &(_, _, start_m, speed_mps, length_m, width_m))| Vehicle {
                route: i,
                start_m,
                speed_mps,
                length_m,
                width_m,
            },
        )
        .collect();
    (layout.map, routes, vehicles)
}

/// Longest lanelet of the intersection's arms and the merge's roads: INTERACTION's lanelets
/// are 6–19 m long at the median by location, 19–40 m at the 90th percentile. (The
/// roundabout keeps its single 60 m arm lanelets: cut into 15 m pieces, road20-cvmap's demo
/// left the road more often, 27 of 30 vehicles within 6 s against 21 over seeds 0–4, and its
/// figures stay comparable across checkpoints as they are; docs/results.md.)
const LANE_PIECE_M: f64 = 15.0;

/// Half the crossing's side: the connectors run inside `[-JUNCTION_M, JUNCTION_M]²`.
const JUNCTION_M: f64 = 10.0;

/// The four-way intersection: arm k points along angle k·π/2; inbound lanes keep right.
/// Connectors join every inbound lane to every other arm's outbound lane (right, straight,
/// left). Routes: (from arm, to arm).
fn intersection_scene() -> (LaneletMap, Vec<Route>, Vec<Vehicle>) {
    let mut lanelets = Vec::new();
    let (mut inbound, mut outbound): ([Vec<usize>; 4], [Vec<usize>; 4]) = Default::default();
    let offset = 0.5 * LANE_WIDTH_M;
    let axis = |k: usize| axes(k as f64 * FRAC_PI_2);
    // A point `d` metres out along arm k, `side` lanes to its left (+1: inbound, driving
    // towards the centre with the right-hand rule, sits on the arm's counter-clockwise side).
    let at = |k: usize, d: f64, side: f64| {
        let (along, left) = axis(k);
        along * d + left * (side * offset)
    };
    for k in 0..4 {
        let id = 3000 + 20 * k as i64;
        let (near, far) = (JUNCTION_M, JUNCTION_M + ARM_LENGTH_M);
        let inbound_line = line(at(k, far, 1.0), at(k, near, 1.0));
        inbound[k] = chain(&mut lanelets, id, &inbound_line, LANE_PIECE_M);
        let outbound_line = line(at(k, near, -1.0), at(k, far, -1.0));
        outbound[k] = chain(&mut lanelets, id + 10, &outbound_line, LANE_PIECE_M);
    }
    let mut connector = [[usize::MAX; 4]; 4];
    for (from, row) in connector.iter_mut().enumerate() {
        for (to, slot) in row.iter_mut().enumerate() {
            if from == to {
                continue;
            }
            let (start, end) = (at(from, JUNCTION_M, 1.0), at(to, JUNCTION_M, -1.0));
            let (a_in, _) = axis(from);
            let (a_out, _) = axis(to);
            // Control points along the travel directions: into the box, out of it.
            let reach = 0.55 * JUNCTION_M;
            let (c1, c2) = (start - a_in * reach, end - a_out * reach);
            *slot = lanelets.len();
            let id = 3200 + 10 * from as i64 + to as i64;
            let mut lane = lanelet(id, "road", bezier([start, c1, c2, end], 16), LANE_WIDTH_M);
            lane.successors.push(outbound[to][0] as u32);
            lanelets.push(lane);
            let last_in = *inbound[from].last().expect("lanes have lanelets");
            lanelets[last_in].successors.push(*slot as u32);
        }
    }
    let route = |from: usize, to: usize| {
        let mut points: Vec<Point> = Vec::new();
        let lanes = inbound[from]
            .iter()
            .chain([&connector[from][to]])
            .chain(&outbound[to]);
        for &lane in lanes {
            points.extend(&lanelets[lane].centre_m);
        }
        Route::new(points)
    };
    // (from, to, metres before the stop line, speed): the ego comes from the south and turns
    // left (west); crossing, following and turning traffic around it.
    let trips: [(usize, usize, f64, f64, f32, f32); 6] = [
        (3, 2, 18.0, 7.0, 4.6, 1.9),
        (1, 3, 22.0, 6.5, 4.4, 1.8),
        (0, 2, 30.0, 8.0, 4.8, 1.9),
        (2, 0, 12.0, 5.5, 4.3, 1.8),
        (3, 0, 34.0, 7.5, 4.5, 1.9),
        (0, 3, -8.0, 6.0, 4.2, 1.8),
    ];
    let routes: Vec<Route> = trips
        .iter()
        .map(|&(from, to, ..)| route(from, to))
        .collect();
    let vehicles = trips
        .iter()
        .enumerate()
        .map(
            |(i, &(_, _, before_m, speed_mps, length_m, width_m))| Vehicle {
                route: i,
                start_m: ARM_LENGTH_M - before_m,
                speed_mps,
                length_m,
                width_m,
            },
        )
        .collect();
    let lanelets = with_shared_bounds(lanelets);
    // An all-way stop, as DR_USA_Intersection_MA's: every inbound lane stops at the box.
    let stop = PriorityRule::new(
        &lanelets,
        5000,
        RuleKind::AllWayStop,
        inbound
            .iter()
            .map(|lanes| *lanes.last().expect("lanes have lanelets") as u32)
            .collect(),
        Vec::new(),
    );
    let map = LaneletMap {
        location: "procedural_intersection".into(),
        lanelets,
        skipped: MapSkips::default(),
        priority_rules: vec![stop],
    };
    (map, routes, vehicles)
}

/// The merge: a one-lane main road along +x (two lanelets, split where the ramp joins) and an
/// on-ramp from the south-west that joins it at x = 0. Routes: 0 main, 1 ramp.
fn merge_scene() -> (LaneletMap, Vec<Route>, Vec<Vehicle>) {
    const MAIN_BEFORE_M: f64 = 90.0;
    const MAIN_AFTER_M: f64 = 90.0;
    let ramp_start = DVec2::new(-70.0, -LANE_WIDTH_M - 18.0);
    let mut lanelets = Vec::new();
    let main_before = chain(
        &mut lanelets,
        4000,
        &line(DVec2::new(-MAIN_BEFORE_M, 0.0), DVec2::ZERO),
        LANE_PIECE_M,
    );
    let main_after = chain(
        &mut lanelets,
        4100,
        &line(DVec2::ZERO, DVec2::new(MAIN_AFTER_M, 0.0)),
        LANE_PIECE_M,
    );
    let ramp_curve = bezier(
        [
            ramp_start,
            DVec2::new(-35.0, ramp_start.y),
            DVec2::new(-25.0, 0.0),
            DVec2::ZERO,
        ],
        72,
    );
    let ramp = chain(&mut lanelets, 4200, &ramp_curve, LANE_PIECE_M);
    for before in [&main_before, &ramp] {
        let last = *before.last().expect("lanes have lanelets");
        lanelets[last].successors.push(main_after[0] as u32);
    }
    let route = |first: &[usize]| {
        let mut points: Vec<Point> = Vec::new();
        for &lane in first.iter().chain(&main_after) {
            points.extend(&lanelets[lane].centre_m);
        }
        Route::new(points)
    };
    let routes = vec![route(&main_before), route(&ramp)];
    // (route, metres before the merge point, speed): the ego on the main road, a ramp vehicle
    // level with it, traffic ahead and behind on both.
    let trips: [(usize, f64, f64, f32, f32); 6] = [
        (0, 30.0, 9.0, 4.6, 1.9),
        (1, 28.0, 8.0, 4.4, 1.8),
        (0, 8.0, 9.5, 4.8, 1.9),
        (0, 52.0, 9.0, 4.5, 1.9),
        (1, 48.0, 8.5, 4.3, 1.8),
        (0, -20.0, 10.0, 4.2, 1.8),
    ];
    let ramp_len = routes[1].length_m() - MAIN_AFTER_M;
    let vehicles = trips
        .iter()
        .map(|&(route, before_m, speed_mps, length_m, width_m)| Vehicle {
            route,
            start_m: if route == 0 { MAIN_BEFORE_M } else { ramp_len } - before_m,
            speed_mps,
            length_m,
            width_m,
        })
        .collect();
    // No priority rule: the ramp runs into the main road alongside it (a zip merge), where no
    // line to give way at lies clear of the main road's traffic.
    let map = LaneletMap {
        location: "procedural_merge".into(),
        lanelets: with_shared_bounds(lanelets),
        skipped: MapSkips::default(),
        priority_rules: Vec::new(),
    };
    (map, routes, vehicles)
}

/// The scene of `vehicles` on `map`: their histories along their routes, the window centred on
/// their mean position at the last observed step, the lane polylines nearest it.
fn scene_of(
    map: LaneletMap,
    routes: Vec<Route>,
    vehicles: &[Vehicle],
    config: &WindowConfig,
    observed_steps: usize,
) -> Result<ProceduralScene> {
    let reference = observed_steps - 1;
    let poses: Vec<Vec<Pose>> = vehicles
        .iter()
        .map(|v| {
            (0..observed_steps)
                .map(|t| {
                    routes[v.route]
                        .pose_at(v.start_m - v.speed_mps * STEP_SECS * (reference - t) as f64)
                })
                .collect()
        })
        .collect();
    // Σ p / n, as road-data centres its windows.
    let n = poses.len() as f64;
    let origin: Point = poses
        .iter()
        .fold(DVec2::ZERO, |sum, p| sum + p[reference].position_m() / n)
        .into();
    let frame = SceneFrame {
        origin_m: origin,
        scale_m: config.position_scale_m,
    };
    let mut states = Vec::with_capacity(poses.len() * observed_steps * 3);
    for agent in &poses {
        let mut previous: Option<f32> = None;
        for p in agent {
            let xy = frame.to_norm([p.x_m, p.y_m]);
            let raw = p.heading_rad as f32;
            let heading = match previous {
                None => road_data::wrap_angle(raw),
                Some(prev) => prev + road_data::wrap_angle(raw - prev),
            };
            previous = Some(heading);
            states.extend([xy[0], xy[1], heading]);
        }
    }
    // Polylines nearest the centre first, as the data pipeline orders them.
    let mut near: Vec<(f64, usize)> = map
        .lanelets
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let d = l
                .centre_m
                .iter()
                .map(|&p| dist(p, origin))
                .fold(f64::INFINITY, f64::min);
            (d, i)
        })
        .filter(|&(d, _)| d <= config.map_radius_m)
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    near.truncate(config.max_polylines);
    let mut polylines = Vec::with_capacity(near.len() * config.polyline_points * 2);
    let mut polyline_lanelet_ids = Vec::with_capacity(near.len());
    for &(_, i) in &near {
        let l = &map.lanelets[i];
        for p in resample(&l.centre_m, config.polyline_points) {
            polylines.extend_from_slice(&frame.to_norm(p));
        }
        polyline_lanelet_ids.push(l.id);
    }
    let window = SceneWindow {
        location: map.location.clone(),
        file: "procedural".into(),
        start_frame: 0,
        frame,
        agents: vehicles.len(),
        steps: observed_steps,
        states,
        valid: vec![true; vehicles.len() * observed_steps],
        track_ids: (1..=vehicles.len() as u32).collect(),
        agent_types: vec![AgentType::Car; vehicles.len()],
        length_m: vehicles.iter().map(|v| v.length_m).collect(),
        width_m: vehicles.iter().map(|v| v.width_m).collect(),
        polyline_points: config.polyline_points,
        polylines,
        polyline_lanelet_ids,
    };
    let ego = ScriptedEgo {
        scene: 0,
        agent: 0,
        route: routes[vehicles[0].route].clone(),
        start_m: vehicles[0].start_m,
        speed_mps: vehicles[0].speed_mps,
    };
    Ok(ProceduralScene {
        map,
        window,
        routes: vehicles.iter().map(|v| routes[v.route].clone()).collect(),
        ego,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lanelets_that_run_on_into_each_other_leave_no_crack() {
        // Across each joint of a lanelet and a successor that runs straight on, from 5 % to
        // 95 % of the way between the bounds, 3 cm before and after the joint: on the road.
        // (The exit curves once left wedges up to 10 cm deep at their straights' starts.)
        for kind in ProceduralMap::ALL {
            let scene = procedural(kind, &WindowConfig::default(), 10).unwrap();
            let map = &scene.map;
            for l in &map.lanelets {
                let [.., before, end] = l.centre_m[..] else {
                    continue;
                };
                let along = (DVec2::from(end) - DVec2::from(before)).normalize();
                for &s in &l.successors {
                    let next = &map.lanelets[s as usize];
                    let start =
                        (DVec2::from(next.centre_m[1]) - DVec2::from(next.centre_m[0])).normalize();
                    if along.dot(start) < 0.99 {
                        continue;
                    }
                    let (left, right) = (
                        DVec2::from(*l.left_m.last().unwrap()),
                        DVec2::from(*l.right_m.last().unwrap()),
                    );
                    for k in 0..=18 {
                        let across = left.lerp(right, 0.05 + 0.05 * f64::from(k));
                        for offset_m in [-0.03, 0.03] {
                            let p = across + along * offset_m;
                            assert!(
                                map.lanelet_at([p.x, p.y]).is_some(),
                                "{}: a crack at {p:?} between lanelets {} and {}",
                                kind.name(),
                                l.id,
                                next.id
                            );
                        }
                    }
                }
            }
        }
    }

    /// Every point of `route` every 0.5 m lies on a lanelet of `map`.
    fn assert_on_map(map: &LaneletMap, route: &Route, what: &str) {
        // Off the lanes' end edges, where point-in-polygon is undecided.
        let mut s = 0.25;
        while s <= route.length_m() - 0.25 {
            let p = route.pose_at(s);
            assert!(
                map.lanelet_at([p.x_m, p.y_m]).is_some(),
                "{what} leaves the map at s = {s:.1} m: {p:?}"
            );
            s += 0.5;
        }
    }

    #[test]
    fn routes_stay_on_the_map() {
        let layout = roundabout_map();
        for from in 0..4 {
            for to in 0..4 {
                if from == to {
                    continue;
                }
                let route = layout.route(from, to);
                assert_on_map(&layout.map, &route, &format!("route {from}→{to}"));
            }
        }
    }

    /// Every vehicle's route of every procedural map runs on its lanes.
    #[test]
    fn every_map_s_routes_stay_on_the_map() {
        for kind in ProceduralMap::ALL {
            let scene = procedural(kind, &WindowConfig::default(), 10).unwrap();
            for (i, route) in scene.routes.iter().enumerate() {
                let what = format!("{}: vehicle {i}'s route", kind.name());
                assert_on_map(&scene.map, route, &what);
            }
        }
    }

    /// A turned scene is the same scene: routes on the turned lanes, the same distances between
    /// the vehicles, headings turned by the angle.
    #[test]
    fn a_turned_scene_is_the_same_scene_turned() {
        let config = WindowConfig::default();
        let angle = 2.0;
        for kind in ProceduralMap::ALL {
            let plain = procedural(kind, &config, 10).unwrap();
            let scene = procedural_turned(kind, &config, 10, angle).unwrap();
            let name = kind.name();
            for (i, route) in scene.routes.iter().enumerate() {
                assert!((route.length_m() - plain.routes[i].length_m()).abs() < 1e-6);
                assert_on_map(
                    &scene.map,
                    route,
                    &format!("{name} turned: vehicle {i}'s route"),
                );
            }
            let (w, w0) = (&scene.window, &plain.window);
            assert_eq!(w.agents, w0.agents);
            assert_eq!(w.polyline_lanelet_ids, w0.polyline_lanelet_ids);
            let metres = |w: &SceneWindow, a: usize| {
                let s = w.state(a, 9).unwrap();
                (
                    DVec2::from(w.frame.to_metres([s[0], s[1]])),
                    f64::from(s[2]),
                )
            };
            for a in 0..w.agents {
                let ((p, h), (p0, h0)) = (metres(w, a), metres(w0, a));
                let turned_heading = road_data::wrap_angle((h - h0 - angle) as f32);
                assert!(turned_heading.abs() < 1e-4, "{name}: agent {a} heading");
                assert!(
                    (p.length() - p0.length()).abs() < 1e-3,
                    "{name}: agent {a} radius"
                );
                for b in 0..a {
                    let (q, q0) = (metres(w, b).0, metres(w0, b).0);
                    assert!(((p - q).length() - (p0 - q0).length()).abs() < 1e-3);
                }
            }
        }
    }

    #[test]
    fn procedural_maps_are_found_by_name() {
        for kind in ProceduralMap::ALL {
            assert_eq!(ProceduralMap::from_name(kind.name()), Some(kind));
        }
        assert_eq!(ProceduralMap::from_name("ring"), None);
        assert_eq!(ProceduralMap::names(), "roundabout, intersection, merge");
    }

    #[test]
    fn every_scene_is_a_valid_window() {
        for kind in ProceduralMap::ALL {
            scene_is_a_valid_window(kind);
        }
    }

    fn scene_is_a_valid_window(kind: ProceduralMap) {
        let config = WindowConfig::default();
        let scene = procedural(kind, &config, 10).unwrap();
        let w = &scene.window;
        assert_eq!(w.steps, 10);
        assert_eq!(w.states.len(), w.agents * w.steps * 3);
        let name = kind.name();
        assert!(
            w.polyline_count() >= 12,
            "{name}: {} polylines",
            w.polyline_count()
        );
        // Histories move at the scripted speeds: 0.1 s apart.
        let a = w.state(0, 8).unwrap();
        let b = w.state(0, 9).unwrap();
        let step_m = f64::from((b[0] - a[0]).hypot(b[1] - a[1])) * config.position_scale_m;
        assert!(
            (step_m - scene.ego.speed_mps * STEP_SECS).abs() < 0.05,
            "{name}: ego moved {step_m} m in a step"
        );
        // No two vehicles overlap at the start.
        let boxes: Vec<_> = (0..w.agents)
            .map(|i| {
                let s = w.state(i, 9).unwrap();
                let p = w.frame.to_metres([s[0], s[1]]);
                Some(crate::geometry::OrientedBox {
                    pose: Pose {
                        x_m: p[0],
                        y_m: p[1],
                        heading_rad: f64::from(s[2]),
                    },
                    length_m: f64::from(w.length_m[i]),
                    width_m: f64::from(w.width_m[i]),
                })
            })
            .collect();
        let overlaps = crate::infractions::collisions(&boxes);
        assert!(
            overlaps.is_empty(),
            "{name}: vehicles overlap at the start: {overlaps:?}"
        );
    }

    #[test]
    fn the_ego_follows_its_route() {
        let scene = roundabout(&WindowConfig::default(), 10).unwrap();
        let mut ego = scene.ego.clone();
        let p0 = ego.pose(0, 0, 0, &[]).unwrap();
        let p1 = ego.pose(0, 0, 1, &[]).unwrap();
        assert!((dist([p0.x_m, p0.y_m], [p1.x_m, p1.y_m]) - 0.7).abs() < 0.05);
        assert!(ego.pose(0, 1, 0, &[]).is_err());
    }
}

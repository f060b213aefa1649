//! A scene built from code, every byte of it redistributable (no INTERACTION data): a
//! four-arm, single-lane roundabout with counter-clockwise (right-hand) traffic, and vehicles
//! whose 1 s histories are generated along routes through it. `road demo` simulates it closed
//! loop with a scripted ego.

use std::f64::consts::FRAC_PI_2;

use road_data::geometry::{Aabb, Point, dist, resample};
use road_data::map::{Lanelet, MapSkips};
use road_data::{AgentType, LaneletMap, SceneFrame, SceneWindow, WindowConfig};

use crate::closed_loop::ExternalDriver;
use crate::{Error, Pose, Result};

/// Seconds per simulated step (INTERACTION's 10 Hz).
pub const STEP_SECS: f64 = 0.1;

/// Ring centre-line radius.
const RING_RADIUS_M: f64 = 20.0;
const RING_WIDTH_M: f64 = 5.0;
const LANE_WIDTH_M: f64 = 3.75;
/// Arms start this far outside the ring's centre line and run `ARM_LENGTH_M`.
const ARM_GAP_M: f64 = 9.0;
const ARM_LENGTH_M: f64 = 60.0;
/// Where connectors meet the ring, either side of an arm's axis.
const MERGE_ANGLE_RAD: f64 = 0.45;

/// A path to drive along, by arc length.
#[derive(Debug, Clone, PartialEq)]
pub struct Route {
    points: Vec<Point>,
    arc_m: Vec<f64>,
}

impl Route {
    /// A route through `points` (consecutive duplicates dropped).
    pub fn new(points: Vec<Point>) -> Self {
        let mut kept: Vec<Point> = Vec::with_capacity(points.len());
        for p in points {
            if kept.last().is_none_or(|&q| dist(p, q) > 1e-6) {
                kept.push(p);
            }
        }
        let mut arc_m = vec![0.0; kept.len()];
        for i in 1..kept.len() {
            arc_m[i] = arc_m[i - 1] + dist(kept[i - 1], kept[i]);
        }
        Self {
            points: kept,
            arc_m,
        }
    }

    pub fn length_m(&self) -> f64 {
        self.arc_m.last().copied().unwrap_or(0.0)
    }

    /// The pose at arc length `s_m`, clamped to the route; the heading is the segment's.
    pub fn pose_at(&self, s_m: f64) -> Pose {
        let s = s_m.clamp(0.0, self.length_m());
        let seg = self
            .arc_m
            .partition_point(|&a| a < s)
            .clamp(1, self.points.len() - 1);
        let (a, b) = (self.points[seg - 1], self.points[seg]);
        let len = self.arc_m[seg] - self.arc_m[seg - 1];
        let t = if len > 0.0 {
            (s - self.arc_m[seg - 1]) / len
        } else {
            0.0
        };
        Pose {
            x_m: a[0] + t * (b[0] - a[0]),
            y_m: a[1] + t * (b[1] - a[1]),
            heading_rad: (b[1] - a[1]).atan2(b[0] - a[0]),
        }
    }
}

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
        let normal = [-(b[1] - a[1]) / len, (b[0] - a[0]) / len];
        let h = 0.5 * width_m;
        left.push([centre[i][0] + h * normal[0], centre[i][1] + h * normal[1]]);
        right.push([centre[i][0] - h * normal[0], centre[i][1] - h * normal[1]]);
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

fn polar(r: f64, angle: f64) -> Point {
    [r * angle.cos(), r * angle.sin()]
}

fn arc(r: f64, from: f64, to: f64) -> Vec<Point> {
    let steps = (((to - from) * r).abs().ceil() as usize).max(2);
    (0..=steps)
        .map(|i| polar(r, from + (to - from) * i as f64 / steps as f64))
        .collect()
}

fn bezier(p: [Point; 4], count: usize) -> Vec<Point> {
    (0..=count)
        .map(|i| {
            let t = i as f64 / count as f64;
            let u = 1.0 - t;
            let w = [u * u * u, 3.0 * u * u * t, 3.0 * u * t * t, t * t * t];
            [
                (0..4).map(|k| w[k] * p[k][0]).sum(),
                (0..4).map(|k| w[k] * p[k][1]).sum(),
            ]
        })
        .collect()
}

fn line(a: Point, b: Point) -> Vec<Point> {
    let steps = (dist(a, b).ceil() as usize).max(2);
    (0..=steps)
        .map(|i| {
            let t = i as f64 / steps as f64;
            [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]
        })
        .collect()
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
    let tangent = |angle: f64| [-angle.sin(), angle.cos()]; // counter-clockwise
    for k in 0..4 {
        let theta = k as f64 * FRAC_PI_2;
        let axis = [theta.cos(), theta.sin()];
        let ccw_side = [-theta.sin(), theta.cos()];
        let offset = 0.5 * LANE_WIDTH_M + 0.25;
        let at = |d: f64, side: f64| {
            [
                d * axis[0] + side * offset * ccw_side[0],
                d * axis[1] + side * offset * ccw_side[1],
            ]
        };
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
                [
                    at(near, 1.0),
                    [
                        at(near, 1.0)[0] - 4.0 * axis[0],
                        at(near, 1.0)[1] - 4.0 * axis[1],
                    ],
                    [p3[0] - 4.0 * t3[0], p3[1] - 4.0 * t3[1]],
                    p3,
                ],
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
                    [p0[0] + 4.0 * t0[0], p0[1] + 4.0 * t0[1]],
                    [
                        at(near, -1.0)[0] - 4.0 * axis[0],
                        at(near, -1.0)[1] - 4.0 * axis[1],
                    ],
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
    Layout {
        map: LaneletMap {
            location: "procedural_roundabout".into(),
            lanelets,
            skipped: MapSkips::default(),
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

/// The demo roundabout with seven vehicles (the ego is agent 0) and 1 s of history each,
/// windowed like INTERACTION data with `config` (`observed_steps` history steps).
pub fn roundabout(config: &WindowConfig, observed_steps: usize) -> Result<ProceduralScene> {
    if observed_steps < 2 {
        return Err(Error::Config(format!(
            "the procedural scene needs at least 2 observed steps, got {observed_steps}"
        )));
    }
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
    let vehicles: [(usize, usize, f64, f64, f32, f32); 7] = [
        (3, 0, inbound_len - 14.0, 7.0, 4.6, 1.9),
        (0, 2, inbound_len + 14.0, 6.0, 4.4, 1.8),
        (2, 3, inbound_len + 30.0, 6.5, 4.8, 1.9),
        (1, 3, inbound_len - 25.0, 8.0, 4.2, 1.8),
        (2, 1, inbound_len - 8.0, 5.0, 4.5, 1.9),
        (0, 3, inbound_len - 30.0, 7.5, 5.0, 2.0),
        (1, 0, inbound_len + 40.0, 6.5, 4.3, 1.8),
    ];
    let routes: Vec<Route> = vehicles
        .iter()
        .map(|&(from, to, ..)| layout.route(from, to))
        .collect();
    let reference = observed_steps - 1;
    let poses: Vec<Vec<Pose>> = vehicles
        .iter()
        .zip(&routes)
        .map(|(&(_, _, s_m, v, ..), route)| {
            (0..observed_steps)
                .map(|t| route.pose_at(s_m - v * STEP_SECS * (reference - t) as f64))
                .collect()
        })
        .collect();
    let n = poses.len() as f64;
    let origin = poses.iter().fold([0.0, 0.0], |acc, p| {
        [acc[0] + p[reference].x_m / n, acc[1] + p[reference].y_m / n]
    });
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
    let mut near: Vec<(f64, usize)> = layout
        .map
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
        let l = &layout.map.lanelets[i];
        for p in resample(&l.centre_m, config.polyline_points) {
            polylines.extend_from_slice(&frame.to_norm(p));
        }
        polyline_lanelet_ids.push(l.id);
    }
    let window = SceneWindow {
        location: layout.map.location.clone(),
        file: "procedural".into(),
        start_frame: 0,
        frame,
        agents: vehicles.len(),
        steps: observed_steps,
        states,
        valid: vec![true; vehicles.len() * observed_steps],
        track_ids: (1..=vehicles.len() as u32).collect(),
        agent_types: vec![AgentType::Car; vehicles.len()],
        length_m: vehicles.iter().map(|v| v.4).collect(),
        width_m: vehicles.iter().map(|v| v.5).collect(),
        polyline_points: config.polyline_points,
        polylines,
        polyline_lanelet_ids,
    };
    let ego = ScriptedEgo {
        scene: 0,
        agent: 0,
        route: routes[0].clone(),
        start_m: vehicles[0].2,
        speed_mps: vehicles[0].3,
    };
    Ok(ProceduralScene {
        map: layout.map,
        window,
        routes,
        ego,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_stay_on_the_map() {
        let layout = roundabout_map();
        for from in 0..4 {
            for to in 0..4 {
                if from == to {
                    continue;
                }
                let route = layout.route(from, to);
                // Off the lanes' end edges, where point-in-polygon is undecided.
                let mut s = 0.25;
                while s <= route.length_m() - 0.25 {
                    let p = route.pose_at(s);
                    assert!(
                        layout.map.lanelet_at([p.x_m, p.y_m]).is_some(),
                        "route {from}→{to} leaves the map at s = {s:.1} m: {p:?}"
                    );
                    s += 0.5;
                }
            }
        }
    }

    #[test]
    fn the_scene_is_a_valid_window() {
        let config = WindowConfig::default();
        let scene = roundabout(&config, 10).unwrap();
        let w = &scene.window;
        assert_eq!(w.steps, 10);
        assert_eq!(w.states.len(), w.agents * w.steps * 3);
        assert!(w.polyline_count() >= 16, "{} polylines", w.polyline_count());
        // Histories move at the scripted speeds: 0.1 s apart.
        let a = w.state(0, 8).unwrap();
        let b = w.state(0, 9).unwrap();
        let step_m = f64::from((b[0] - a[0]).hypot(b[1] - a[1])) * config.position_scale_m;
        assert!(
            (step_m - 0.7).abs() < 0.05,
            "ego moved {step_m} m in a step"
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
        assert!(crate::infractions::collisions(&boxes).is_empty());
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

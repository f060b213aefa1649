//! The give-way rule (`road_sched::GiveWay`) on a map's priority rules: a side road's vehicle
//! gives way to the main road's at a crossing read from a Lanelet2 map, and two vehicles at the
//! procedural intersection's all-way stop stop at their lines and cross one after the other. The model is replaced by
//! `common`'s engine, whose plans drive straight on, so that only the rule moves anyone.

use std::f64::consts::FRAC_PI_2;

use std::path::Path;

use road_data::LaneletMap;
use road_planner::collision_guard::GuardAction;
use road_sched::{GiveWay, PlannerSpec};
use road_sim::closed_loop::SceneTick;
use road_sim::procedural::ProceduralMap;

mod common;
use common::{run_on_lanes, run_turning};

const RULE: GiveWay = GiveWay {
    approach_m: 30.0,
    gap_secs: 3.0,
    brake_mps2: 3.0,
    stop_secs: 1.0,
};

fn planner(rule: Option<GiveWay>) -> PlannerSpec {
    PlannerSpec {
        give_way: rule,
        obs_noise: Some(0.0),
        ..PlannerSpec::default()
    }
}

/// `ticks`, each vehicle's front: how far past its line (negative: short of it), `line_at`
/// giving the line's distance along the vehicle's way from its centre's coordinate.
fn front_past(ticks: &[SceneTick], agent: usize, past: impl Fn(f64, f64) -> f64) -> Vec<f64> {
    ticks
        .iter()
        .map(|t| past(t.poses[agent].x_m, t.poses[agent].y_m))
        .collect()
}

/// A crossing as a Lanelet2 map: a main road eastwards along y = 0 and a side road
/// northwards along x = 0 across it, both 3.5 m wide, the side road giving way (a
/// `right_of_way` element) at the main road's edge, y = −1.75.
fn crossing() -> LaneletMap {
    // Near (0, 0) a degree of latitude is 110 574 m, of longitude 111 320 m.
    let node = |id: u32, x: f64, y: f64| {
        format!(
            "<node id=\"{id}\" lat=\"{}\" lon=\"{}\"/>\n",
            y / 110_574.0,
            x / 111_320.0
        )
    };
    let way = |id: u32, a: u32, b: u32| {
        format!("<way id=\"{id}\"><nd ref=\"{a}\"/><nd ref=\"{b}\"/></way>\n")
    };
    let lanelet = |id: u32, left: u32, right: u32| {
        format!(
            "<relation id=\"{id}\"><member type=\"way\" ref=\"{left}\" role=\"left\"/><member type=\"way\" ref=\"{right}\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/></relation>\n"
        )
    };
    let h = 1.75;
    let mut osm = String::from("<?xml version=\"1.0\"?>\n<osm version=\"0.6\">\n");
    for (id, x, y) in [
        (1, -60.0, h),
        (2, -h, h),
        (3, 60.0, h),
        (4, -60.0, -h),
        (5, -h, -h),
        (6, 60.0, -h),
        (7, -h, -60.0),
        (8, h, -60.0),
        (9, h, -h),
        (10, -h, 60.0),
        (11, h, h),
        (12, h, 60.0),
    ] {
        osm += &node(id, x, y);
    }
    // Main road: in (to x = −1.75) and on; side road: in (to the main road's edge), across it,
    // and on.
    for (id, a, b) in [
        (20, 1, 2),
        (21, 4, 5),
        (22, 2, 3),
        (23, 5, 6),
        (24, 7, 5),
        (25, 8, 9),
        (26, 5, 2),
        (27, 9, 11),
        (28, 2, 10),
        (29, 11, 12),
    ] {
        osm += &way(id, a, b);
    }
    for (id, left, right) in [
        (30, 20, 21),
        (31, 22, 23),
        (32, 24, 25),
        (33, 26, 27),
        (34, 28, 29),
    ] {
        osm += &lanelet(id, left, right);
    }
    osm += "<relation id=\"40\"><member type=\"relation\" ref=\"30\" role=\"right_of_way\"/><member type=\"relation\" ref=\"32\" role=\"yield\"/><tag k=\"type\" v=\"regulatory_element\"/><tag k=\"subtype\" v=\"right_of_way\"/></relation>\n</osm>\n";
    LaneletMap::parse(&osm, Path::new("crossing.osm"), "crossing").unwrap()
}

#[test]
fn a_side_road_vehicle_gives_way_to_the_main_road_s() {
    let map = crossing();
    assert_eq!(map.priority_rules.len(), 1);
    // Vehicle 0 (4.6 m) on the main road 20 m before the crossing, vehicle 1 (4.4 m) on the
    // side road 12 m before it, both driven on at 8 m/s: the main road's is due in under 3 s.
    let stands = [(0, -22.0, 0.0, 0.0), (1, 0.0, -12.0, FRAC_PI_2)];
    let run = |rule| run_on_lanes(&map, &planner(rule), &stands, 60, 8.0);
    // The main road's vehicle clear of the side road; the side road's front past its line.
    let main_clear = |t: &SceneTick| t.poses[0].x_m - 2.3 > h_m();
    let side_front = |t: &SceneTick| t.poses[1].y_m + 2.2 + h_m();

    let free = run(None);
    assert!(
        free.iter().any(|t| side_front(t) > 0.0 && !main_clear(t)),
        "the premise: it would cross first"
    );

    let ruled = run(Some(RULE));
    for (tick, t) in ruled.iter().enumerate() {
        if !main_clear(t) {
            assert!(
                side_front(t) <= 0.0,
                "tick {tick}: the side road's front {:.2} m past its line before the main \
                 road's vehicle passed",
                side_front(t)
            );
        }
    }
    assert!(
        ruled
            .iter()
            .any(|t| t.guarded.contains(&(1, GuardAction::GaveWay))),
        "held by the rule"
    );
    assert!(
        !ruled.iter().any(|t| t.guarded.iter().any(|&(a, _)| a == 0)),
        "the main road's vehicle is never held"
    );
    // Then it goes.
    let last = ruled.last().unwrap();
    assert!(last.poses[1].y_m > 5.0, "it went on: {:?}", last.poses[1]);
    assert!(ruled.iter().all(|t| t.collisions.is_empty()));
}

/// Half the crossing's lane width, metres.
fn h_m() -> f64 {
    1.75
}

#[test]
fn at_an_all_way_stop_both_stop_and_cross_one_after_the_other() {
    // The intersection's all-way stop lines lie 10 m from its centre. Vehicle 0 (4.6 m) comes
    // from the east (y = 1.875, heading west), vehicle 1 (4.4 m) from the south (x = 1.875,
    // heading north), both 20 m out and driven on at 8 m/s: their paths cross in the box at the
    // same time.
    let stands = [
        (0, 20.0, 1.875, std::f64::consts::PI),
        (1, 1.875, -20.0, FRAC_PI_2),
    ];
    let run = |rule| {
        run_turning(
            ProceduralMap::Intersection,
            &planner(rule),
            &[0, 1],
            &stands,
            200,
            8.0,
            0.0,
            None,
        )
    };
    let free = run(None);
    assert!(
        free.iter().any(|t| !t.collisions.is_empty()),
        "the premise: without the rule they collide"
    );

    let ruled = run(Some(RULE));
    assert!(
        ruled.iter().all(|t| t.collisions.is_empty()),
        "no collision"
    );
    // Fronts past the lines: vehicle 0's line at x = 10 (driving −x), vehicle 1's at y = −10.
    let past0 = front_past(&ruled, 0, |x, _| 10.0 - (x - 2.3));
    let past1 = front_past(&ruled, 1, |_, y| (y + 2.2) + 10.0);
    let crossed = |past: &[f64]| past.iter().position(|&p| p > 0.0).expect("it crossed");
    let (cross0, cross1) = (crossed(&past0), crossed(&past1));
    // Each stood at its line for the rule's second before crossing.
    for (agent, past, cross) in [(0, &past0, cross0), (1, &past1, cross1)] {
        let stood = (1..cross)
            .filter(|&k| {
                let (a, b) = (ruled[k - 1].poses[agent], ruled[k].poses[agent]);
                (b.x_m - a.x_m).hypot(b.y_m - a.y_m) / 0.1 < 0.3 && past[k] > -1.0
            })
            .count();
        assert!(
            stood >= 10,
            "vehicle {agent} stood {stood} ticks at its line"
        );
    }
    // The lower index first (they arrived together); the other not before it left the box.
    assert!(cross0 < cross1, "{cross0} {cross1}");
    let out_of_box = ruled
        .iter()
        .position(|t| t.poses[0].x_m + 2.3 < -10.0)
        .expect("vehicle 0 crossed the box");
    assert!(
        cross1 > out_of_box,
        "vehicle 1 crossed at tick {cross1}, vehicle 0 left the box at {out_of_box}"
    );
}

//! Lanelet2 `.osm` maps: projection, lanelet bounds and centre lines, topology, and the lane
//! queries later used for off-road checks.

use std::collections::HashMap;
use std::path::Path;

use glam::DVec2;
use serde::{Deserialize, Serialize};

use crate::geometry::{
    Aabb, Point, SegmentGrid, dist, point_in_polygon, polyline_length, resample,
};
use crate::{Error, Result};

pub mod rules;
use rules::{PriorityRule, RuleKind};

/// UTM zone of every INTERACTION map (its lat/lon sit around (0, 0)).
pub const UTM_ZONE: u8 = 31;

/// Bound endpoints closer than this are the same point for topology (metres).
const TOPOLOGY_TOLERANCE_M: f64 = 0.1;
/// Spacing of the resampled bounds used for the centre line (metres).
const CENTRE_SPACING_M: f64 = 1.0;

/// Projects WGS84 lat/lon (degrees) to the INTERACTION frame: UTM zone 31 minus the projection
/// of (0, 0). Returns `[x_m, y_m]` (east, north).
pub fn project(lat_deg: f64, lon_deg: f64) -> Point {
    // UTM adds a false northing of 10 000 km south of the equator (the `utm` crate from
    // latitude 0 down): take it off so that the frame is continuous across the equator.
    let utm = |lat, lon| {
        let (north, east, _) = utm::to_utm_wgs84(lat, lon, UTM_ZONE);
        let north = if north > 5_000_000.0 {
            north - 10_000_000.0
        } else {
            north
        };
        (north, east)
    };
    let (north, east) = utm(lat_deg, lon_deg);
    let (north0, east0) = utm(0.0, 0.0);
    [east - east0, north - north0]
}

/// One lanelet: bounds in driving direction, centre line and topology (indices into
/// [`LaneletMap::lanelets`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Lanelet {
    /// OSM relation id.
    pub id: i64,
    pub subtype: Option<String>,
    pub left_way: i64,
    pub right_way: i64,
    pub left_m: Vec<Point>,
    pub right_m: Vec<Point>,
    /// Mean of the two bounds resampled to the same count (about one point per metre).
    pub centre_m: Vec<Point>,
    /// Lanelets that continue this one (bounds' ends meet their starts).
    pub successors: Vec<u32>,
    /// Lanelets that share a bound with this one.
    pub neighbours: Vec<u32>,
    pub bounds: Aabb,
}

impl Lanelet {
    /// The lanelet's area: left bound, then right bound backwards.
    pub fn polygon(&self) -> Vec<Point> {
        self.left_m
            .iter()
            .chain(self.right_m.iter().rev())
            .copied()
            .collect()
    }

    pub fn contains(&self, p: Point) -> bool {
        self.bounds.contains(p) && point_in_polygon(p, &self.polygon())
    }
}

/// What a map load skipped on purpose (reported, never silent).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapSkips {
    /// Relations that are not lanelets (regulatory elements, multipolygons, ...).
    pub non_lanelet_relations: usize,
}

/// A location's lanelets.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LaneletMap {
    pub location: String,
    pub lanelets: Vec<Lanelet>,
    pub skipped: MapSkips,
    /// Its priority rules (`right_of_way` and `all_way_stop` regulatory elements).
    #[serde(default)]
    pub priority_rules: Vec<PriorityRule>,
}

impl LaneletMap {
    pub fn load(path: &Path, location: &str) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::io(path, source))?;
        Self::parse(&text, path, location)
    }

    /// Parses OSM XML text; `path` only names the input in errors.
    pub fn parse(text: &str, path: &Path, location: &str) -> Result<Self> {
        let map_err = |element: String, reason: String| Error::Map {
            path: path.to_owned(),
            element,
            reason,
        };
        let doc = roxmltree::Document::parse(text)
            .map_err(|e| map_err("document".into(), e.to_string()))?;
        let line_of = |n: roxmltree::Node| doc.text_pos_at(n.range().start).row;

        let id_attr = |n: roxmltree::Node, what: &str| -> Result<i64> {
            let raw = n.attribute("id").ok_or_else(|| {
                map_err(
                    format!("{what} at line {}", line_of(n)),
                    "missing attribute `id`".into(),
                )
            })?;
            raw.parse().map_err(|_| {
                map_err(
                    format!("{what} at line {}", line_of(n)),
                    format!("bad id `{raw}`"),
                )
            })
        };

        let mut nodes: HashMap<i64, Point> = HashMap::new();
        let mut ways: HashMap<i64, Vec<i64>> = HashMap::new();
        let mut relations = Vec::new();
        for n in doc.root_element().children().filter(|n| n.is_element()) {
            match n.tag_name().name() {
                "node" => {
                    let id = id_attr(n, "node")?;
                    let coord = |key: &str| -> Result<f64> {
                        let raw = n.attribute(key).ok_or_else(|| {
                            map_err(
                                format!("node {id} (line {})", line_of(n)),
                                format!("missing attribute `{key}`"),
                            )
                        })?;
                        match raw.parse::<f64>() {
                            Ok(v) if v.is_finite() => Ok(v),
                            _ => Err(map_err(
                                format!("node {id} (line {})", line_of(n)),
                                format!("bad {key} `{raw}`"),
                            )),
                        }
                    };
                    nodes.insert(id, project(coord("lat")?, coord("lon")?));
                }
                "way" => {
                    let id = id_attr(n, "way")?;
                    let refs = n
                        .children()
                        .filter(|c| c.has_tag_name("nd"))
                        .map(|c| {
                            c.attribute("ref")
                                .and_then(|r| r.parse::<i64>().ok())
                                .ok_or_else(|| {
                                    map_err(
                                        format!("way {id} (line {})", line_of(c)),
                                        "nd without a numeric `ref`".into(),
                                    )
                                })
                        })
                        .collect::<Result<Vec<_>>>()?;
                    ways.insert(id, refs);
                }
                "relation" => relations.push(n),
                _ => {}
            }
        }

        let way_points = |way: i64, lanelet: i64| -> Result<Vec<Point>> {
            let refs = ways.get(&way).ok_or_else(|| {
                map_err(
                    format!("relation {lanelet}"),
                    format!("member way {way} does not exist"),
                )
            })?;
            let pts = refs
                .iter()
                .map(|r| {
                    nodes.get(r).copied().ok_or_else(|| {
                        map_err(
                            format!("way {way}"),
                            format!("node {r} does not exist (used by lanelet {lanelet})"),
                        )
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            if pts.len() < 2 {
                return Err(map_err(
                    format!("way {way}"),
                    format!("a lanelet bound needs two nodes, has {}", pts.len()),
                ));
            }
            Ok(pts)
        };

        let mut lanelets = Vec::new();
        let mut skipped = MapSkips::default();
        let mut rules = Vec::new();
        for r in relations {
            let id = id_attr(r, "relation")?;
            let tag = |k: &str| {
                r.children()
                    .find(|c| c.has_tag_name("tag") && c.attribute("k") == Some(k))
                    .and_then(|c| c.attribute("v"))
                    .map(str::to_owned)
            };
            if tag("type").as_deref() != Some("lanelet") {
                skipped.non_lanelet_relations += 1;
                let kind = match tag("subtype").as_deref() {
                    Some("right_of_way") => Some(RuleKind::Yield),
                    Some("all_way_stop") => Some(RuleKind::AllWayStop),
                    _ => None,
                };
                if let (Some("regulatory_element"), Some(kind)) = (tag("type").as_deref(), kind) {
                    let members = |role: &str| -> Vec<String> {
                        r.children()
                            .filter(|c| {
                                c.has_tag_name("member")
                                    && c.attribute("role") == Some(role)
                                    && c.attribute("type") == Some("relation")
                            })
                            .map(|c| c.attribute("ref").unwrap_or_default().to_owned())
                            .collect()
                    };
                    rules.push((
                        id,
                        line_of(r),
                        kind,
                        members("yield"),
                        members("right_of_way"),
                    ));
                }
                continue;
            }
            let member = |role: &str| -> Result<i64> {
                r.children()
                    .find(|c| {
                        c.has_tag_name("member")
                            && c.attribute("role") == Some(role)
                            && c.attribute("type") == Some("way")
                    })
                    .and_then(|c| c.attribute("ref"))
                    .and_then(|v| v.parse().ok())
                    .ok_or_else(|| {
                        map_err(
                            format!("relation {id} (line {})", line_of(r)),
                            format!("lanelet without a `{role}` way"),
                        )
                    })
            };
            let (left_way, right_way) = (member("left")?, member("right")?);
            let (left, right) =
                orient_bounds(way_points(left_way, id)?, way_points(right_way, id)?);
            let longest = polyline_length(&left).max(polyline_length(&right));
            let count = ((longest / CENTRE_SPACING_M).ceil() as usize + 1)
                .max(left.len())
                .max(right.len())
                .max(2);
            let (l, rr) = (resample(&left, count), resample(&right, count));
            let centre = l
                .iter()
                .zip(&rr)
                .map(|(&a, &b)| DVec2::from(a).midpoint(DVec2::from(b)).into())
                .collect();
            let bounds = Aabb::of(&[left.as_slice(), right.as_slice()].concat());
            lanelets.push(Lanelet {
                id,
                subtype: tag("subtype"),
                left_way,
                right_way,
                left_m: left,
                right_m: right,
                centre_m: centre,
                successors: Vec::new(),
                neighbours: Vec::new(),
                bounds,
            });
        }
        if lanelets.is_empty() {
            return Err(map_err("document".into(), "no lanelet relations".into()));
        }
        lanelets.sort_by_key(|l| l.id);
        link_topology(&mut lanelets);
        let mut priority_rules = Vec::new();
        for (id, line, kind, yielding, priority) in rules {
            let index = |role: &str, raw: &str| -> Result<u32> {
                raw.parse::<i64>()
                    .ok()
                    .and_then(|r| lanelets.binary_search_by_key(&r, |l| l.id).ok())
                    .map(|i| i as u32)
                    .ok_or_else(|| {
                        map_err(
                            format!("regulatory element {id} (line {line})"),
                            format!("its `{role}` member `{raw}` is not a lanelet of the map"),
                        )
                    })
            };
            let yield_lanelets = yielding
                .iter()
                .map(|r| index("yield", r))
                .collect::<Result<Vec<_>>>()?;
            let priority_lanelets = priority
                .iter()
                .map(|r| index("right_of_way", r))
                .collect::<Result<Vec<_>>>()?;
            if yield_lanelets.is_empty() {
                return Err(map_err(
                    format!("regulatory element {id} (line {line})"),
                    "a right of way or all-way stop without a `yield` lanelet".into(),
                ));
            }
            if kind == RuleKind::Yield && priority_lanelets.is_empty() {
                return Err(map_err(
                    format!("regulatory element {id} (line {line})"),
                    "a right of way without a `right_of_way` lanelet".into(),
                ));
            }
            priority_rules.push(PriorityRule::new(
                &lanelets,
                id,
                kind,
                yield_lanelets,
                priority_lanelets,
            ));
        }
        Ok(Self {
            location: location.to_owned(),
            lanelets,
            skipped,
            priority_rules,
        })
    }

    /// Index of a lanelet that contains `p`, if any (off-road when none).
    pub fn lanelet_at(&self, p: Point) -> Option<usize> {
        self.lanelets.iter().position(|l| l.contains(p))
    }

    /// The lanelets that `keep` accepts, in their order, their successors and neighbours
    /// among them (links to the others dropped): a crop of the map, whose open ends are where
    /// the crop cuts the road.
    pub fn crop(&self, keep: impl Fn(&Lanelet) -> bool) -> LaneletMap {
        let mut new_index = vec![None; self.lanelets.len()];
        let mut lanelets = Vec::new();
        for (i, l) in self.lanelets.iter().enumerate() {
            if keep(l) {
                new_index[i] = Some(lanelets.len() as u32);
                lanelets.push(l.clone());
            }
        }
        let remap = |links: &[u32]| -> Vec<u32> {
            links
                .iter()
                .filter_map(|&j| new_index.get(j as usize).copied().flatten())
                .collect()
        };
        for l in &mut lanelets {
            l.successors = remap(&l.successors);
            l.neighbours = remap(&l.neighbours);
        }
        // A rule stays while one of its yield lanelets does.
        let priority_rules = self
            .priority_rules
            .iter()
            .filter_map(|g| {
                let yield_lanelets = remap(&g.yield_lanelets);
                (!yield_lanelets.is_empty()).then(|| PriorityRule {
                    yield_lanelets,
                    priority_lanelets: remap(&g.priority_lanelets),
                    junction: g
                        .junction
                        .iter()
                        .filter_map(|(l, c)| new_index[*l as usize].map(|l| (l, remap(c))))
                        .collect(),
                    ..g.clone()
                })
            })
            .collect();
        LaneletMap {
            location: self.location.clone(),
            lanelets,
            skipped: self.skipped.clone(),
            priority_rules,
        }
    }

    /// A grid over every centre-line segment, for distance queries.
    pub fn centre_grid(&self, cell_m: f64) -> SegmentGrid {
        let segments = self
            .lanelets
            .iter()
            .flat_map(|l| l.centre_m.windows(2).map(|w| (w[0], w[1])))
            .collect();
        SegmentGrid::new(segments, cell_m)
    }

    /// Centre lines resampled to `points` points each, in lanelet order: the map polylines.
    pub fn centre_polylines(&self, points: usize) -> Vec<Vec<Point>> {
        self.lanelets
            .iter()
            .map(|l| resample(&l.centre_m, points))
            .collect()
    }
}

/// A lanelet's bounds in its driving direction. Lanelet2 stores a bound as the way it is
/// (a way shared by two lanelets runs against one of them) and reads the direction from the
/// bounds' sides, as its loader's `geometry::align` does: the left bound lies left of the
/// driving direction. First the right bound is turned to run along the left one (their ends
/// pair up), then both are turned when the left one lies on the right. Taking the left way's
/// own direction instead, as this parser once did, drove 12 of DR_USA_Intersection_MA's 66
/// lanelets and 6 of DR_USA_Roundabout_FT's 48 the wrong way (issue 39's inflow then started
/// vehicles head-on into the traffic).
fn orient_bounds(mut left: Vec<Point>, mut right: Vec<Point>) -> (Vec<Point>, Vec<Point>) {
    let straight = dist(left[0], right[0]) + dist(left[left.len() - 1], right[right.len() - 1]);
    let crossed = dist(left[0], right[right.len() - 1]) + dist(left[left.len() - 1], right[0]);
    if crossed < straight {
        right.reverse();
    }
    // Σ over the resampled pairs of (direction × (left − right)): positive when the left
    // bound lies on the left.
    let count = left.len().max(right.len()).max(2);
    let (l, r) = (resample(&left, count), resample(&right, count));
    let side: f64 = (0..count - 1)
        .map(|i| {
            let mid = |k: usize| DVec2::from(l[k]).midpoint(DVec2::from(r[k]));
            let direction = mid(i + 1) - mid(i);
            let across = DVec2::from(l[i]) - DVec2::from(r[i]);
            direction.perp_dot(across)
        })
        .sum();
    if side < 0.0 {
        left.reverse();
        right.reverse();
    }
    (left, right)
}

fn link_topology(lanelets: &mut [Lanelet]) {
    let ends: Vec<(Point, Point, Point, Point, i64, i64)> = lanelets
        .iter()
        .map(|l| {
            (
                l.left_m[0],
                l.right_m[0],
                *l.left_m.last().unwrap(),
                *l.right_m.last().unwrap(),
                l.left_way,
                l.right_way,
            )
        })
        .collect();
    for (i, a) in ends.iter().enumerate() {
        for (j, b) in ends.iter().enumerate() {
            if i == j {
                continue;
            }
            if dist(a.2, b.0) < TOPOLOGY_TOLERANCE_M && dist(a.3, b.1) < TOPOLOGY_TOLERANCE_M {
                lanelets[i].successors.push(j as u32);
            }
            if a.4 == b.4 || a.4 == b.5 || a.5 == b.4 || a.5 == b.5 {
                lanelets[i].neighbours.push(j as u32);
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Two lanelets in a row and one beside the first, ~1e-5 degrees ≈ 1.1 m apart.
    pub(crate) fn fixture_osm() -> String {
        let d = 0.000_036; // ≈ 4 m
        let mut s = String::from("<?xml version=\"1.0\"?>\n<osm version=\"0.6\">\n");
        // Three rows of nodes (y = 0, 1, 2 lanes) and three columns (x = 0, 1, 2 segments).
        for row in 0..3 {
            for col in 0..3 {
                let id = 1000 + row * 10 + col;
                s += &format!(
                    "  <node id=\"{id}\" lat=\"{}\" lon=\"{}\" />\n",
                    row as f64 * d,
                    col as f64 * d * 3.0
                );
            }
        }
        let way = |id: i64, a: i64, b: i64| {
            format!("  <way id=\"{id}\"><nd ref=\"{a}\"/><nd ref=\"{b}\"/></way>\n")
        };
        s += &way(1, 1010, 1011); // middle row, col 0→1
        s += &way(2, 1000, 1001); // bottom row
        s += &way(3, 1011, 1012);
        s += &way(4, 1002, 1001); // stored backwards on purpose
        s += &way(5, 1020, 1021); // top row
        let lanelet = |id: i64, l: i64, r: i64| {
            format!(
                "  <relation id=\"{id}\"><member type=\"way\" ref=\"{l}\" role=\"left\"/><member type=\"way\" ref=\"{r}\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/><tag k=\"subtype\" v=\"road\"/></relation>\n"
            )
        };
        s += &lanelet(30000, 1, 2);
        s += &lanelet(30001, 3, 4);
        s += &lanelet(30002, 5, 1);
        s += "  <relation id=\"50000\"><tag k=\"type\" v=\"regulatory_element\"/></relation>\n</osm>\n";
        s
    }

    #[test]
    fn projection_of_known_points() {
        // (0, 0) maps to the origin by construction; 0.001° of latitude is ≈ 110.6 m north.
        assert_eq!(project(0.0, 0.0), [0.0, 0.0]);
        let p = project(0.001, 0.0);
        assert!(p[0].abs() < 0.5 && (p[1] - 110.6).abs() < 0.5, "{p:?}");
        let q = project(0.0, 0.001);
        assert!((q[0] - 111.0).abs() < 1.0 && q[1].abs() < 1e-6, "{q:?}");
        // Continuous across the equator (no false-northing jump).
        let s = project(-0.0001, 0.0);
        assert!((s[1] + 11.06).abs() < 0.1, "{s:?}");
    }

    #[test]
    fn parses_lanelets_centres_and_topology() {
        let map = LaneletMap::parse(&fixture_osm(), Path::new("fixture.osm"), "FIX").unwrap();
        assert_eq!(map.lanelets.len(), 3);
        assert_eq!(map.skipped.non_lanelet_relations, 1);
        let first = &map.lanelets[0];
        // The centre runs midway between the bounds, ~2 m north of the bottom row.
        let c = first.centre_m[0];
        assert!((c[1] - 2.0).abs() < 0.05 && c[0].abs() < 0.05, "{c:?}");
        // The backwards right bound of lanelet 30001 was turned round.
        assert!(map.lanelets[1].right_m[0][0] < map.lanelets[1].right_m[1][0]);
        assert_eq!(first.successors, vec![1]);
        assert_eq!(first.neighbours, vec![2]);
        assert!(map.lanelet_at(c).is_some());
        assert_eq!(map.lanelet_at([c[0] + 1.0, c[1] + 20.0]), None);
        let grid = map.centre_grid(5.0);
        assert!(grid.nearest_distance([c[0] + 1.0, c[1] + 0.5]).unwrap() < 0.51);
    }

    #[test]
    fn the_driving_direction_follows_the_bounds_sides() {
        // Both ways run east, the left one along the south row: a lanelet whose left bound lies
        // south of it drives west (Lanelet2's `align`), whichever way its ways were drawn.
        let d = 0.000_036;
        let mut osm = String::from("<?xml version=\"1.0\"?>\n<osm version=\"0.6\">\n");
        for (id, lat, lon) in [
            (1, 0.0, 0.0),
            (2, 0.0, 3.0 * d),
            (3, d, 0.0),
            (4, d, 3.0 * d),
        ] {
            osm += &format!("  <node id=\"{id}\" lat=\"{lat}\" lon=\"{lon}\" />\n");
        }
        osm += "  <way id=\"10\"><nd ref=\"1\"/><nd ref=\"2\"/></way>\n";
        osm += "  <way id=\"11\"><nd ref=\"4\"/><nd ref=\"3\"/></way>\n";
        osm += "  <relation id=\"20\"><member type=\"way\" ref=\"10\" role=\"left\"/><member type=\"way\" ref=\"11\" role=\"right\"/><tag k=\"type\" v=\"lanelet\"/></relation>\n</osm>\n";
        let map = LaneletMap::parse(&osm, Path::new("sides.osm"), "SIDES").unwrap();
        let lanelet = &map.lanelets[0];
        let (first, last) = (
            lanelet.centre_m[0],
            lanelet.centre_m[lanelet.centre_m.len() - 1],
        );
        assert!(
            last[0] < first[0] - 10.0,
            "drives west: {first:?} → {last:?}"
        );
        // Both bounds run west too, the left one still the south row.
        assert!(lanelet.left_m[0][0] > lanelet.left_m[1][0]);
        assert!(lanelet.right_m[0][0] > lanelet.right_m[1][0]);
        assert!(lanelet.left_m[0][1] < lanelet.right_m[0][1]);
    }

    #[test]
    fn right_of_way_and_all_way_stop_elements_are_read_by_lanelet() {
        // 30002 (the top row) gives way to 30000 (the middle row); an all-way stop on 30000.
        let osm = fixture_osm().replace(
            "  <relation id=\"50000\"><tag k=\"type\" v=\"regulatory_element\"/></relation>\n",
            "  <relation id=\"50000\"><member type=\"relation\" ref=\"30000\" role=\"right_of_way\"/><member type=\"relation\" ref=\"30002\" role=\"yield\"/><member type=\"way\" ref=\"3\" role=\"ref_line\"/><tag k=\"type\" v=\"regulatory_element\"/><tag k=\"subtype\" v=\"right_of_way\"/></relation>\n  <relation id=\"50001\"><member type=\"relation\" ref=\"30000\" role=\"yield\"/><tag k=\"type\" v=\"regulatory_element\"/><tag k=\"subtype\" v=\"all_way_stop\"/></relation>\n  <relation id=\"50002\"><tag k=\"type\" v=\"regulatory_element\"/><tag k=\"subtype\" v=\"speed_limit\"/></relation>\n",
        );
        let map = LaneletMap::parse(&osm, Path::new("rules.osm"), "FIX").unwrap();
        assert_eq!(map.skipped.non_lanelet_relations, 3);
        assert_eq!(
            map.priority_rules.len(),
            2,
            "the speed limit is no priority rule"
        );
        let (yields, stop) = (&map.priority_rules[0], &map.priority_rules[1]);
        assert_eq!(yields.kind, RuleKind::Yield);
        assert_eq!(
            (
                yields.yield_lanelets.clone(),
                yields.priority_lanelets.clone()
            ),
            (vec![2], vec![0])
        );
        assert!(yields.junction.is_empty(), "30002 leads nowhere");
        assert_eq!(stop.kind, RuleKind::AllWayStop);
        assert!(stop.yields_on(0) && !stop.yields_on(1));
        // The lanelet after 30000 is the all-way stop's junction, alone: no conflicts.
        assert_eq!(stop.junction, vec![(1, vec![])]);
        // A crop keeps the rules whose yield lanelets it keeps, re-indexed.
        let crop = map.crop(|l| l.id != 30001);
        assert_eq!(crop.priority_rules.len(), 2);
        assert!(crop.priority_rules[1].junction.is_empty());
        let crop = map.crop(|l| l.id != 30002);
        assert_eq!(
            crop.priority_rules.len(),
            1,
            "the right of way lost its yield lanelet"
        );

        // A member that is no lanelet is named.
        let bad = osm.replace("ref=\"30002\" role=\"yield\"", "ref=\"777\" role=\"yield\"");
        let err = LaneletMap::parse(&bad, Path::new("rules.osm"), "FIX")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("regulatory element 50000")
                && err.contains("`yield` member `777`")
                && err.contains("rules.osm"),
            "{err}"
        );
        let bad = osm.replace(
            "ref=\"30000\" role=\"right_of_way\"",
            "ref=\"30001\" role=\"refers\"",
        );
        let err = LaneletMap::parse(&bad, Path::new("rules.osm"), "FIX")
            .unwrap_err()
            .to_string();
        assert!(err.contains("without a `right_of_way` lanelet"), "{err}");
    }

    #[test]
    fn a_crop_keeps_the_links_among_its_lanelets() {
        let map = LaneletMap::parse(&fixture_osm(), Path::new("fixture.osm"), "FIX").unwrap();
        // Without the first lanelet: the second (its successor) has no predecessor left, the
        // third (its neighbour) no neighbour.
        let crop = map.crop(|l| l.id != 30000);
        assert_eq!(
            crop.lanelets.iter().map(|l| l.id).collect::<Vec<_>>(),
            vec![30001, 30002]
        );
        assert!(crop.lanelets.iter().all(|l| l.successors.is_empty()));
        assert!(crop.lanelets.iter().all(|l| l.neighbours.is_empty()));
        // Without the third: the first keeps its successor, now at index 1.
        let crop = map.crop(|l| l.id != 30002);
        assert_eq!(crop.lanelets[0].successors, vec![1]);
        assert!(crop.lanelets[0].neighbours.is_empty());
    }

    #[test]
    fn missing_node_and_way_are_named() {
        let bad = fixture_osm().replace("<nd ref=\"1012\"/>", "<nd ref=\"999\"/>");
        let err = LaneletMap::parse(&bad, Path::new("bad.osm"), "FIX")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("node 999 does not exist")
                && err.contains("bad.osm")
                && err.contains("way 3"),
            "{err}"
        );
        let bad = fixture_osm().replace("ref=\"5\" role=\"left\"", "ref=\"77\" role=\"left\"");
        let err = LaneletMap::parse(&bad, Path::new("bad.osm"), "FIX")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("member way 77 does not exist") && err.contains("relation 30002"),
            "{err}"
        );
        let bad = fixture_osm().replace("lat=\"0\" lon=\"0\"", "lat=\"NaN\" lon=\"0\"");
        let err = LaneletMap::parse(&bad, Path::new("bad.osm"), "FIX")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("node 1000") && err.contains("bad lat"),
            "{err}"
        );
    }
}

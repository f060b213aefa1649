// Agent-centric maps (`model.agent_map`): for each agent row (b, a), the K lane polylines of
// its scene nearest its anchor (its state at the anchor slot, zero where not valid there),
// written in its anchor frame. CPU reference: `road_model::agent_map::agent_maps` (the order:
// valid polylines before padding, then least squared distance from the anchor to any point,
// then the lower index).
//
// One invocation per agent row; the polylines' distances sit in a private array, so a scene
// offers at most MAX_POLYLINES of them (the engine checks `map_polylines` against it). Each
// agent row picks from the map of its scene `agent_scene[row]`: a plain batch's row of scene b
// holds b; a packed batch (several scenes' agents in one of its scenes) holds the map's.

struct Params {
    rows: u32,        // B·A agent rows
    agents: u32,      // A
    slots: u32,       // W
    anchor_slot: u32,
    polylines: u32,   // P per scene
    points: u32,      // Q per polyline
    picked: u32,      // K ≤ P per agent
    heading_scale: f32,
}

const MAX_POLYLINES: u32 = 128u;
const FAR: f32 = 3.0e38;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> x: array<f32>;          // [B, A, W, 3]
@group(0) @binding(2) var<storage, read> valid: array<f32>;      // [B, A, W]
@group(0) @binding(3) var<storage, read> map_points: array<f32>; // [M, P, Q, 2]: M map scenes
@group(0) @binding(4) var<storage, read> map_valid: array<f32>;  // [M, P]
@group(0) @binding(5) var<storage, read> agent_scene: array<u32>;     // [B·A]: map scene
@group(0) @binding(6) var<storage, read_write> out_points: array<f32>; // [B·A, K, Q, 2]
@group(0) @binding(7) var<storage, read_write> out_valid: array<f32>;  // [B·A, K]

@compute @workgroup_size(64)
fn pick_agent_maps(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let row = gid.x + gid.y * groups.x * 64u;
    if (row >= params.rows) {
        return;
    }
    let scene = agent_scene[row];
    let token = row * params.slots + params.anchor_slot;
    let v = valid[token];
    let ax = x[3u * token] * v;
    let ay = x[3u * token + 1u] * v;
    let heading = x[3u * token + 2u] * v / params.heading_scale;
    let c = cos(heading);
    let s = sin(heading);
    let p_count = params.polylines;
    let q_count = params.points;

    var nearest: array<f32, MAX_POLYLINES>;
    var taken: array<bool, MAX_POLYLINES>;
    for (var p = 0u; p < p_count; p++) {
        var best = FAR;
        for (var q = 0u; q < q_count; q++) {
            let at = 2u * ((scene * p_count + p) * q_count + q);
            let dx = map_points[at] - ax;
            let dy = map_points[at + 1u] - ay;
            best = min(best, dx * dx + dy * dy);
        }
        nearest[p] = best;
        taken[p] = false;
    }
    for (var k = 0u; k < params.picked; k++) {
        // The first polyline in (padding, distance, index) order not taken yet.
        var pick = p_count;
        var pick_padding = true;
        var pick_distance = FAR;
        for (var p = 0u; p < p_count; p++) {
            if (taken[p]) {
                continue;
            }
            let padding = map_valid[scene * p_count + p] <= 0.0;
            let before = pick == p_count
                || (!padding && pick_padding)
                || (padding == pick_padding && nearest[p] < pick_distance);
            if (before) {
                pick = p;
                pick_padding = padding;
                pick_distance = nearest[p];
            }
        }
        taken[pick] = true;
        out_valid[row * params.picked + k] = map_valid[scene * p_count + pick];
        for (var q = 0u; q < q_count; q++) {
            let src = 2u * ((scene * p_count + pick) * q_count + q);
            let dst = 2u * ((row * params.picked + k) * q_count + q);
            let dx = map_points[src] - ax;
            let dy = map_points[src + 1u] - ay;
            out_points[dst] = c * dx + s * dy;
            out_points[dst + 1u] = c * dy - s * dx;
        }
    }
}

// Compact sub-batches (`GpuStepEngine`): rows of a batch's per-scene regions (states, flags,
// agent embeddings, maps) gathered into a sub-batch and its results scattered back, one
// dispatch per region instead of a copy command per scene and region.
//
// A region is rows of `row_floats` floats. `row_map` has one entry per row of the sub-batch
// side: the batch side's row, or NONE. `gather_rows`: dst[r] = src[row_map[r]], zeros where
// NONE (so a sub-batch row no scene fills holds no agent). `scatter_rows`: dst[row_map[r]] =
// src[r], nothing where NONE. One invocation per float of the sub-batch side; the mapped row is
// checked against the other side's length, so that the kernels bound their own indices.

struct Params {
    rows: u32,       // sub-batch rows (row_map's length)
    row_floats: u32, // floats per row
    _pad0: u32,
    _pad1: u32,
}

const NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read> row_map: array<u32>; // [rows]
@group(0) @binding(3) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(64)
fn gather_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if (i >= params.rows * params.row_floats) {
        return;
    }
    let source_row = row_map[i / params.row_floats];
    var value = 0.0;
    if (source_row != NONE) {
        let at = source_row * params.row_floats + i % params.row_floats;
        if (at < arrayLength(&src)) {
            value = src[at];
        }
    }
    dst[i] = value;
}

@compute @workgroup_size(64)
fn scatter_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if (i >= params.rows * params.row_floats) {
        return;
    }
    let target_row = row_map[i / params.row_floats];
    if (target_row == NONE) {
        return;
    }
    let at = target_row * params.row_floats + i % params.row_floats;
    if (at < arrayLength(&dst)) {
        dst[at] = src[i];
    }
}

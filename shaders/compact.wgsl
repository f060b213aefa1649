// Compact sub-batches (`GpuStepEngine`): rows of a batch's per-scene regions (states, flags,
// agent embeddings, maps) gathered into a sub-batch and its results scattered back, the regions
// that share a row map in one dispatch (up to three), instead of a copy command per scene and
// region.
//
// Region k is rows of `floats[k]` floats (0: no such region). `row_map` has one entry per row
// of the sub-batch side: the batch side's row, or NONE. Gathers: dst_k[r] = src_k[row_map[r]],
// zeros where NONE (so a sub-batch row no scene fills holds no agent). Scatters: dst_k[row_map[r]]
// = src_k[r], nothing where NONE. One invocation per float of a sub-batch row's regions, region
// by region; every index is checked against its array's length, so that the kernels bound their
// own indices. The entry points `gather_rows`, `gather_rows_2`, `gather_rows_3`, `scatter_rows`
// and `scatter_rows_2` move the first 1, 2 or 3 regions: each binds only its own buffers.

struct Params {
    rows: u32,        // sub-batch rows (row_map's length)
    floats0: u32,     // floats per row of each region
    floats1: u32,
    floats2: u32,
}

const NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> row_map: array<u32>; // [rows]
@group(0) @binding(2) var<storage, read> src0: array<f32>;
@group(0) @binding(3) var<storage, read_write> dst0: array<f32>;
@group(0) @binding(4) var<storage, read> src1: array<f32>;
@group(0) @binding(5) var<storage, read_write> dst1: array<f32>;
@group(0) @binding(6) var<storage, read> src2: array<f32>;
@group(0) @binding(7) var<storage, read_write> dst2: array<f32>;

fn invocation(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 64u;
}

// The float `j` of sub-batch row `r` in a region of `floats` floats per row: (sub-batch index,
// batch index or NONE).
fn at(r: u32, j: u32, floats: u32) -> vec2<u32> {
    let batch_row = row_map[r];
    var batch_at = NONE;
    if (batch_row != NONE) {
        batch_at = batch_row * floats + j;
    }
    return vec2<u32>(r * floats + j, batch_at);
}

fn gather0(r: u32, j: u32) {
    let i = at(r, j, params.floats0);
    var value = 0.0;
    if (i.y < arrayLength(&src0)) {
        value = src0[i.y];
    }
    if (i.x < arrayLength(&dst0)) {
        dst0[i.x] = value;
    }
}

fn gather1(r: u32, j: u32) {
    let i = at(r, j, params.floats1);
    var value = 0.0;
    if (i.y < arrayLength(&src1)) {
        value = src1[i.y];
    }
    if (i.x < arrayLength(&dst1)) {
        dst1[i.x] = value;
    }
}

fn gather2(r: u32, j: u32) {
    let i = at(r, j, params.floats2);
    var value = 0.0;
    if (i.y < arrayLength(&src2)) {
        value = src2[i.y];
    }
    if (i.x < arrayLength(&dst2)) {
        dst2[i.x] = value;
    }
}

fn scatter0(r: u32, j: u32) {
    let i = at(r, j, params.floats0);
    if (i.y < arrayLength(&dst0) && i.x < arrayLength(&src0)) {
        dst0[i.y] = src0[i.x];
    }
}

fn scatter1(r: u32, j: u32) {
    let i = at(r, j, params.floats1);
    if (i.y < arrayLength(&dst1) && i.x < arrayLength(&src1)) {
        dst1[i.y] = src1[i.x];
    }
}

@compute @workgroup_size(64)
fn gather_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let per_row = params.floats0;
    if (i >= params.rows * per_row) {
        return;
    }
    gather0(i / per_row, i % per_row);
}

@compute @workgroup_size(64)
fn gather_rows_2(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let per_row = params.floats0 + params.floats1;
    if (i >= params.rows * per_row) {
        return;
    }
    let r = i / per_row;
    let j = i % per_row;
    if (j < params.floats0) {
        gather0(r, j);
    } else {
        gather1(r, j - params.floats0);
    }
}

@compute @workgroup_size(64)
fn gather_rows_3(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let per_row = params.floats0 + params.floats1 + params.floats2;
    if (i >= params.rows * per_row) {
        return;
    }
    let r = i / per_row;
    let j = i % per_row;
    if (j < params.floats0) {
        gather0(r, j);
    } else if (j < params.floats0 + params.floats1) {
        gather1(r, j - params.floats0);
    } else {
        gather2(r, j - params.floats0 - params.floats1);
    }
}

@compute @workgroup_size(64)
fn scatter_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let per_row = params.floats0;
    if (i >= params.rows * per_row) {
        return;
    }
    scatter0(i / per_row, i % per_row);
}

@compute @workgroup_size(64)
fn scatter_rows_2(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let per_row = params.floats0 + params.floats1;
    if (i >= params.rows * per_row) {
        return;
    }
    let r = i / per_row;
    let j = i % per_row;
    if (j < params.floats0) {
        scatter0(r, j);
    } else {
        scatter1(r, j - params.floats0);
    }
}

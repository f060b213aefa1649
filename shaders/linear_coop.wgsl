// The linear layer of `linear.wgsl` on the tensor cores: cooperative matrices of f16 inputs and
// f32 sums (naga's `coop_mat16x16` and `coop_mat8x8`, Vulkan's VK_KHR_cooperative_matrix). The
// engine runs it only where the adapter offers one of the two configurations and subgroups of
// one fixed width, and only for layers whose inputs and outputs are multiples of 16 (every layer
// of the model's blocks); `linear_f16.wgsl` has the same rounding everywhere else.
// A workgroup is one subgroup (`COOP_LANES` invocations, set to the adapter's width) and
// computes a block of rows × outputs as 2 × 6 accumulator tiles: 32 × 96 with 16 × 16 tiles
// (`linear_coop`: NVIDIA's), 16 × 48 with 8 × 8 ones (`linear_coop8`: Mesa 26's lavapipe's). Per
// K-chunk of 96 it stages its rows' inputs in workgroup memory as f16 (standardised first under
// `norm`: the statistics from one pass over each row), then per tile of K loads the two row
// tiles from there and the six weight tiles straight from the f16 weights (2–10 MB: they stay
// in L2), and multiplies. The sums go through workgroup memory to the shared epilogue (bias,
// ReLU, residual, parts) in f32.
// Cooperative operations need control flow uniform across the subgroup: every branch around
// them depends on the workgroup alone, and weight tiles past `out_dim` read tile 0 (valid
// memory; their results are not stored). Every index and stride is a `let` of its own.
// Params, bindings 0, 1, 3, 4, `row_stats` and `store4`: `common/linear_io.wgsl`, prepended.
@group(0) @binding(2) var<storage, read> w: array<f16>; // [out, in]

// Invocations of a workgroup: the adapter's subgroup width (the engine sets it).
override COOP_LANES: u32 = 32u;
const COOP_K: u32 = 96u;
// Halves per staged row: 96 + 8, a multiple of 16 bytes (cooperative loads want it) that
// shifts each row's banks.
const COOP_X_STRIDE: u32 = 104u;
// Floats per row of the result tile: 96 + 4, likewise.
const COOP_OUT_STRIDE: u32 = 100u;

var<workgroup> coop_x: array<f16, 3328>;     // [32, COOP_X_STRIDE]: n(x) as f16
var<workgroup> coop_out: array<f32, 3200>;   // [32, COOP_OUT_STRIDE]: the sums
var<workgroup> coop_stats: array<vec2<f32>, 32>; // [32]: (mean, 1/σ) of the block's rows

// The statistics of the block's rows (identity without a norm), for `coop_stage`.
fn coop_row_stats(row0: u32, block_rows: u32, lane: u32) {
    for (var r = lane; r < block_rows; r += COOP_LANES) {
        var stats = vec2<f32>(0.0, 1.0);
        if (params.norm == 1u && row0 + r < params.rows) {
            stats = row_stats(row0 + r);
        }
        coop_stats[r] = stats;
    }
}

// Stages rows row0.. × k0..k0 + 96 of n(x) as f16: consecutive k in consecutive lanes; zero
// past the rows and past in_dim.
fn coop_stage(row0: u32, k0: u32, block_rows: u32, lane: u32) {
    for (var e = lane; e < block_rows * COOP_K; e += COOP_LANES) {
        let r = e / COOP_K;
        let k = e % COOP_K;
        var value = 0.0;
        if (row0 + r < params.rows && k0 + k < params.in_dim) {
            let s = coop_stats[r];
            value = (x[(row0 + r) * params.in_dim + k0 + k] - s.x) * s.y;
        }
        coop_x[r * COOP_X_STRIDE + k] = f16(value);
    }
}

// The block's sums in `coop_out`, plus the bias, through the shared epilogue: a lane a quad.
// out_dim is a multiple of 16: a quad below it is whole.
fn coop_epilogue(row0: u32, out0: u32, block_rows: u32, block_outs: u32, lane: u32) {
    let quads = block_outs / 4u;
    for (var q = lane; q < block_rows * quads; q += COOP_LANES) {
        let r = q / quads;
        let c = (q % quads) * 4u;
        let row = row0 + r;
        let o = out0 + c;
        if (row < params.rows && o < params.out_dim) {
            let t = r * COOP_OUT_STRIDE + c;
            let sums = vec4<f32>(coop_out[t], coop_out[t + 1u], coop_out[t + 2u], coop_out[t + 3u]);
            store4(row, o, sums + vec4<f32>(b[o], b[o + 1u], b[o + 2u], b[o + 3u]));
        }
    }
}

// 16 × 16 × 16 tiles: a block of 32 rows × 96 outputs.
@compute @workgroup_size(COOP_LANES)
fn linear_coop(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    // Uniform across the workgroup (computed here: naga's uniformity analysis does not follow
    // a helper's result): the grid may hold more groups than blocks.
    let out_blocks = (params.out_dim + 96u - 1u) / 96u;
    let block = wid.x + wid.y * groups.x;
    if (block >= out_blocks * ((params.rows + 32u - 1u) / 32u)) {
        return;
    }
    let row0 = (block / out_blocks) * 32u;
    let out0 = (block % out_blocks) * 96u;
    coop_row_stats(row0, 32u, lane);
    // The six weight tiles' first outputs; past out_dim, tile 0's.
    let o0 = out0;
    let o1 = select(out0, out0 + 16u, out0 + 16u < params.out_dim);
    let o2 = select(out0, out0 + 32u, out0 + 32u < params.out_dim);
    let o3 = select(out0, out0 + 48u, out0 + 48u < params.out_dim);
    let o4 = select(out0, out0 + 64u, out0 + 64u < params.out_dim);
    let o5 = select(out0, out0 + 80u, out0 + 80u < params.out_dim);
    var c00 = coop_mat16x16<f32, C>();
    var c01 = coop_mat16x16<f32, C>();
    var c02 = coop_mat16x16<f32, C>();
    var c03 = coop_mat16x16<f32, C>();
    var c04 = coop_mat16x16<f32, C>();
    var c05 = coop_mat16x16<f32, C>();
    var c10 = coop_mat16x16<f32, C>();
    var c11 = coop_mat16x16<f32, C>();
    var c12 = coop_mat16x16<f32, C>();
    var c13 = coop_mat16x16<f32, C>();
    var c14 = coop_mat16x16<f32, C>();
    var c15 = coop_mat16x16<f32, C>();
    let in_dim = params.in_dim;
    for (var k0 = 0u; k0 < in_dim; k0 += COOP_K) {
        workgroupBarrier(); // the statistics written; the previous chunk's loads done
        coop_stage(row0, k0, 32u, lane);
        workgroupBarrier();
        let kn = min(COOP_K, in_dim - k0);
        for (var kk = 0u; kk < kn; kk += 16u) {
            let xs = COOP_X_STRIDE;
            let ia0 = kk;
            let ia1 = 16u * COOP_X_STRIDE + kk;
            let a0 = coopLoadT<coop_mat16x16<f16, A>>(&coop_x[ia0], xs);
            let a1 = coopLoadT<coop_mat16x16<f16, A>>(&coop_x[ia1], xs);
            // B[k][n] = w[o + n, k]: w's rows are B's columns (column-major, stride in_dim).
            let k = k0 + kk;
            let ib0 = o0 * in_dim + k;
            let ib1 = o1 * in_dim + k;
            let ib2 = o2 * in_dim + k;
            let ib3 = o3 * in_dim + k;
            let ib4 = o4 * in_dim + k;
            let ib5 = o5 * in_dim + k;
            let b0 = coopLoad<coop_mat16x16<f16, B>>(&w[ib0], in_dim);
            c00 = coopMultiplyAdd(a0, b0, c00);
            c10 = coopMultiplyAdd(a1, b0, c10);
            let b1 = coopLoad<coop_mat16x16<f16, B>>(&w[ib1], in_dim);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c11 = coopMultiplyAdd(a1, b1, c11);
            let b2 = coopLoad<coop_mat16x16<f16, B>>(&w[ib2], in_dim);
            c02 = coopMultiplyAdd(a0, b2, c02);
            c12 = coopMultiplyAdd(a1, b2, c12);
            let b3 = coopLoad<coop_mat16x16<f16, B>>(&w[ib3], in_dim);
            c03 = coopMultiplyAdd(a0, b3, c03);
            c13 = coopMultiplyAdd(a1, b3, c13);
            let b4 = coopLoad<coop_mat16x16<f16, B>>(&w[ib4], in_dim);
            c04 = coopMultiplyAdd(a0, b4, c04);
            c14 = coopMultiplyAdd(a1, b4, c14);
            let b5 = coopLoad<coop_mat16x16<f16, B>>(&w[ib5], in_dim);
            c05 = coopMultiplyAdd(a0, b5, c05);
            c15 = coopMultiplyAdd(a1, b5, c15);
        }
    }
    let os = COOP_OUT_STRIDE;
    let i00 = 0u;
    let i01 = 16u;
    let i02 = 32u;
    let i03 = 48u;
    let i04 = 64u;
    let i05 = 80u;
    let i10 = 16u * COOP_OUT_STRIDE;
    let i11 = 16u * COOP_OUT_STRIDE + 16u;
    let i12 = 16u * COOP_OUT_STRIDE + 32u;
    let i13 = 16u * COOP_OUT_STRIDE + 48u;
    let i14 = 16u * COOP_OUT_STRIDE + 64u;
    let i15 = 16u * COOP_OUT_STRIDE + 80u;
    coopStoreT(c00, &coop_out[i00], os);
    coopStoreT(c01, &coop_out[i01], os);
    coopStoreT(c02, &coop_out[i02], os);
    coopStoreT(c03, &coop_out[i03], os);
    coopStoreT(c04, &coop_out[i04], os);
    coopStoreT(c05, &coop_out[i05], os);
    coopStoreT(c10, &coop_out[i10], os);
    coopStoreT(c11, &coop_out[i11], os);
    coopStoreT(c12, &coop_out[i12], os);
    coopStoreT(c13, &coop_out[i13], os);
    coopStoreT(c14, &coop_out[i14], os);
    coopStoreT(c15, &coop_out[i15], os);
    workgroupBarrier();
    coop_epilogue(row0, out0, 32u, 96u, lane);
}

// 8 × 8 × 8 tiles: a block of 16 rows × 48 outputs, the same steps.
@compute @workgroup_size(COOP_LANES)
fn linear_coop8(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    // Uniform across the workgroup (computed here: naga's uniformity analysis does not follow
    // a helper's result): the grid may hold more groups than blocks.
    let out_blocks = (params.out_dim + 48u - 1u) / 48u;
    let block = wid.x + wid.y * groups.x;
    if (block >= out_blocks * ((params.rows + 16u - 1u) / 16u)) {
        return;
    }
    let row0 = (block / out_blocks) * 16u;
    let out0 = (block % out_blocks) * 48u;
    coop_row_stats(row0, 16u, lane);
    let o0 = out0;
    let o1 = select(out0, out0 + 8u, out0 + 8u < params.out_dim);
    let o2 = select(out0, out0 + 16u, out0 + 16u < params.out_dim);
    let o3 = select(out0, out0 + 24u, out0 + 24u < params.out_dim);
    let o4 = select(out0, out0 + 32u, out0 + 32u < params.out_dim);
    let o5 = select(out0, out0 + 40u, out0 + 40u < params.out_dim);
    var c00 = coop_mat8x8<f32, C>();
    var c01 = coop_mat8x8<f32, C>();
    var c02 = coop_mat8x8<f32, C>();
    var c03 = coop_mat8x8<f32, C>();
    var c04 = coop_mat8x8<f32, C>();
    var c05 = coop_mat8x8<f32, C>();
    var c10 = coop_mat8x8<f32, C>();
    var c11 = coop_mat8x8<f32, C>();
    var c12 = coop_mat8x8<f32, C>();
    var c13 = coop_mat8x8<f32, C>();
    var c14 = coop_mat8x8<f32, C>();
    var c15 = coop_mat8x8<f32, C>();
    let in_dim = params.in_dim;
    for (var k0 = 0u; k0 < in_dim; k0 += COOP_K) {
        workgroupBarrier();
        coop_stage(row0, k0, 16u, lane);
        workgroupBarrier();
        let kn = min(COOP_K, in_dim - k0);
        for (var kk = 0u; kk < kn; kk += 8u) {
            let xs = COOP_X_STRIDE;
            let ia0 = kk;
            let ia1 = 8u * COOP_X_STRIDE + kk;
            let a0 = coopLoadT<coop_mat8x8<f16, A>>(&coop_x[ia0], xs);
            let a1 = coopLoadT<coop_mat8x8<f16, A>>(&coop_x[ia1], xs);
            let k = k0 + kk;
            let ib0 = o0 * in_dim + k;
            let ib1 = o1 * in_dim + k;
            let ib2 = o2 * in_dim + k;
            let ib3 = o3 * in_dim + k;
            let ib4 = o4 * in_dim + k;
            let ib5 = o5 * in_dim + k;
            let b0 = coopLoad<coop_mat8x8<f16, B>>(&w[ib0], in_dim);
            c00 = coopMultiplyAdd(a0, b0, c00);
            c10 = coopMultiplyAdd(a1, b0, c10);
            let b1 = coopLoad<coop_mat8x8<f16, B>>(&w[ib1], in_dim);
            c01 = coopMultiplyAdd(a0, b1, c01);
            c11 = coopMultiplyAdd(a1, b1, c11);
            let b2 = coopLoad<coop_mat8x8<f16, B>>(&w[ib2], in_dim);
            c02 = coopMultiplyAdd(a0, b2, c02);
            c12 = coopMultiplyAdd(a1, b2, c12);
            let b3 = coopLoad<coop_mat8x8<f16, B>>(&w[ib3], in_dim);
            c03 = coopMultiplyAdd(a0, b3, c03);
            c13 = coopMultiplyAdd(a1, b3, c13);
            let b4 = coopLoad<coop_mat8x8<f16, B>>(&w[ib4], in_dim);
            c04 = coopMultiplyAdd(a0, b4, c04);
            c14 = coopMultiplyAdd(a1, b4, c14);
            let b5 = coopLoad<coop_mat8x8<f16, B>>(&w[ib5], in_dim);
            c05 = coopMultiplyAdd(a0, b5, c05);
            c15 = coopMultiplyAdd(a1, b5, c15);
        }
    }
    let os = COOP_OUT_STRIDE;
    let i00 = 0u;
    let i01 = 8u;
    let i02 = 16u;
    let i03 = 24u;
    let i04 = 32u;
    let i05 = 40u;
    let i10 = 8u * COOP_OUT_STRIDE;
    let i11 = 8u * COOP_OUT_STRIDE + 8u;
    let i12 = 8u * COOP_OUT_STRIDE + 16u;
    let i13 = 8u * COOP_OUT_STRIDE + 24u;
    let i14 = 8u * COOP_OUT_STRIDE + 32u;
    let i15 = 8u * COOP_OUT_STRIDE + 40u;
    coopStoreT(c00, &coop_out[i00], os);
    coopStoreT(c01, &coop_out[i01], os);
    coopStoreT(c02, &coop_out[i02], os);
    coopStoreT(c03, &coop_out[i03], os);
    coopStoreT(c04, &coop_out[i04], os);
    coopStoreT(c05, &coop_out[i05], os);
    coopStoreT(c10, &coop_out[i10], os);
    coopStoreT(c11, &coop_out[i11], os);
    coopStoreT(c12, &coop_out[i12], os);
    coopStoreT(c13, &coop_out[i13], os);
    coopStoreT(c14, &coop_out[i14], os);
    coopStoreT(c15, &coop_out[i15], os);
    workgroupBarrier();
    coop_epilogue(row0, out0, 16u, 48u, lane);
}

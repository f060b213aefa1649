// The linear layer of `linear.wgsl` on the tensor cores: cooperative 16 × 16 × 16 matrices of
// f16 inputs and f32 sums (naga's `coop_mat16x16`, Vulkan's VK_KHR_cooperative_matrix). The
// engine runs it only where the adapter offers that configuration and subgroups 32 wide, and
// only for layers whose inputs and outputs are multiples of 16 (every layer of the model's
// blocks); `linear_f16.wgsl` has the same numerics everywhere else.
// A workgroup is one subgroup of 32 invocations and computes 32 rows × 96 outputs as 2 × 6
// accumulator tiles. Per K-chunk of 96 it stages its rows' inputs in workgroup memory as f16
// (standardised first under `norm`: the statistics from one pass over each row, an invocation
// a row), then per 16 of K loads the two row tiles from there and the six weight tiles straight
// from the f16 weights (2–10 MB: they stay in L2), and multiplies. The sums go through
// workgroup memory to the shared epilogue (bias, ReLU, residual, parts) in f32.
// Cooperative operations need control flow uniform across the subgroup: every branch around
// them depends on the workgroup alone, and weight tiles past `out_dim` read tile 0 (valid
// memory; their results are not stored). Every index and stride is a `let` of its own.
// Params, bindings 0, 1, 3, 4, `row_stats` and `store4`: `common/linear_io.wgsl`, prepended.
@group(0) @binding(2) var<storage, read> w: array<f16>; // [out, in]

const COOP_ROWS: u32 = 32u;
const COOP_OUTS: u32 = 96u;
const COOP_K: u32 = 96u;
// Halves per staged row: 96 + 8, a multiple of 16 bytes (cooperative loads want it) that
// shifts each row's banks.
const COOP_X_STRIDE: u32 = 104u;
// Floats per row of the result tile: 96 + 4, likewise.
const COOP_OUT_STRIDE: u32 = 100u;

var<workgroup> coop_x: array<f16, 3328>;     // [COOP_ROWS, COOP_X_STRIDE]: n(x) as f16
var<workgroup> coop_out: array<f32, 3200>;   // [COOP_ROWS, COOP_OUT_STRIDE]: the sums
var<workgroup> coop_stats: array<vec2<f32>, 32>; // [COOP_ROWS]: (mean, 1/σ)

@compute @workgroup_size(32)
fn linear_coop(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let out_blocks = (params.out_dim + COOP_OUTS - 1u) / COOP_OUTS;
    let row_blocks = (params.rows + COOP_ROWS - 1u) / COOP_ROWS;
    let block = wid.x + wid.y * groups.x;
    // Uniform across the workgroup: the grid may hold more groups than blocks.
    if (block >= out_blocks * row_blocks) {
        return;
    }
    let row0 = (block / out_blocks) * COOP_ROWS;
    let out0 = (block % out_blocks) * COOP_OUTS;

    var stats = vec2<f32>(0.0, 1.0);
    if (params.norm == 1u && row0 + lid < params.rows) {
        stats = row_stats(row0 + lid);
    }
    coop_stats[lid] = stats;

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
        // Stage rows row0.. × k0..k0 + 96: consecutive k in consecutive invocations; zero past
        // the rows and past in_dim.
        for (var i = 0u; i < COOP_ROWS * COOP_K / 32u; i++) {
            let e = lid + 32u * i;
            let r = e / COOP_K;
            let k = e % COOP_K;
            var value = 0.0;
            if (row0 + r < params.rows && k0 + k < in_dim) {
                let s = coop_stats[r];
                value = (x[(row0 + r) * in_dim + k0 + k] - s.x) * s.y;
            }
            coop_x[r * COOP_X_STRIDE + k] = f16(value);
        }
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

    // The sums, row-major, then the epilogue: 32 rows × 24 quads, 24 quads an invocation.
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
    for (var i = 0u; i < COOP_ROWS * COOP_OUTS / 128u; i++) {
        let q = lid + 32u * i;
        let r = q / (COOP_OUTS / 4u);
        let c = (q % (COOP_OUTS / 4u)) * 4u;
        let row = row0 + r;
        let o = out0 + c;
        if (row < params.rows && o < params.out_dim) {
            // out_dim is a multiple of 16: the quad is whole.
            let t = r * COOP_OUT_STRIDE + c;
            let sums = vec4<f32>(coop_out[t], coop_out[t + 1u], coop_out[t + 2u], coop_out[t + 3u]);
            store4(row, o, sums + vec4<f32>(b[o], b[o + 1u], b[o + 2u], b[o + 3u]));
        }
    }
}

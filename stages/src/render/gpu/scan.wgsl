// Kernel `scan`: in-place exclusive prefix sum of data[0 .. P.n) by blocks of
// 1024 (4 per thread); each block's total goes to sums[block]. The host scans
// `sums` the same way and adds it back with `scan_add` (integer sums: exact,
// so the order cannot matter).

@group(0) @binding(0) var<uniform> P: Small;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

var<workgroup> sh: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32,
        @builtin(num_workgroups) nwg: vec3<u32>) {
    let blk = wid.x + wid.y * nwg.x;
    let base = blk * 1024u + lid * 4u;
    var v: array<u32, 4>;
    var local = 0u;
    for (var k = 0u; k < 4u; k++) {
        let idx = base + k;
        var x = 0u;
        if idx < P.n {
            x = data[idx];
        }
        v[k] = local;
        local += x;
    }
    sh[lid] = local;
    for (var d = 1u; d < 256u; d *= 2u) {
        workgroupBarrier();
        var t = 0u;
        if lid >= d {
            t = sh[lid - d];
        }
        workgroupBarrier();
        sh[lid] += t;
    }
    workgroupBarrier();
    let excl = sh[lid] - local;
    for (var k = 0u; k < 4u; k++) {
        let idx = base + k;
        if idx < P.n {
            data[idx] = excl + v[k];
        }
    }
    if lid == 255u {
        sums[blk] = sh[255];
    }
}

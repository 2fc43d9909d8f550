// Kernel `emit`: one thread per Gaussian: writes the key (tile, depth bits,
// index, slot) of each of its (tile, Gaussian) instances at slots
// offsets[i] .. offsets[i] + count, in increasing tile order.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> S: array<Splat>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> keys: array<vec4<u32>>;
// Unused here; declared so that the shared helpers compile.
var<private> G: array<f32, 1>;

fn visit(tile: u32, gi: u32, slot: u32) {
    keys[slot] = vec4<u32>(tile, bitcast<u32>(S[gi].f1.x), gi, slot);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n {
        return;
    }
    let sp = S[i];
    if (bitcast<u32>(sp.cov.w) & 1u) == 0u {
        return;
    }
    _ = for_each_tile(sp, i, offsets[i]);
}

// Kernel `blend_gather`: one thread per Gaussian: the sum of its instance
// slots' blend sums (`blend`) in tile order, as the CPU sums them.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> rec: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> sums: array<vec4<f32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n {
        return;
    }
    var t = vec4<f32>(0.0);
    for (var s = offsets[i]; s < offsets[i + 1u]; s++) {
        t += rec[s];
    }
    sums[i] = t;
}

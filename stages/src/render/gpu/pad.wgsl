// Kernel `pad`: the sort's padding keys (greater than every real key) in
// keys[P.a .. P.n).

@group(0) @binding(0) var<uniform> P: Small;
@group(0) @binding(1) var<storage, read_write> keys: array<vec4<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg) + P.a;
    if i >= P.n {
        return;
    }
    keys[i] = vec4<u32>(0xffffffffu, 0xffffffffu, 0xffffffffu, 0xffffffffu);
}

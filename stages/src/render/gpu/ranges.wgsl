// Kernel `ranges`: the instance range [start, end) of every tile from the
// sorted keys (ranges is zeroed first, so empty tiles get [0, 0)).

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> ranges: array<vec2<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n_inst {
        return;
    }
    let t = keys[i].x;
    if i == 0u || keys[i - 1u].x != t {
        ranges[t].x = i;
    }
    if i + 1u == P.n_inst || keys[i + 1u].x != t {
        ranges[t].y = i + 1u;
    }
}

// Kernel `scan_add`: data[i] += sums[i / 1024] (second half of `scan`).

@group(0) @binding(0) var<uniform> P: Small;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read> sums: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n {
        return;
    }
    data[i] += sums[i / 1024u];
}

// Kernel `sort`: one compare-exchange step (k, j) of a bitonic sort of the
// instance keys by (tile, depth bits, Gaussian index). The keys are unique
// (the index breaks every tie), so the order is total and the result does not
// depend on the algorithm: it is exactly the CPU's (tile-major, then depth,
// then index) instance order. Depths are positive (z >= near > 0), so their
// bit patterns order like the floats.

@group(0) @binding(0) var<uniform> P: Small; // n, k, j
@group(0) @binding(1) var<storage, read_write> keys: array<vec4<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = lin_id(gid, nwg);
    if i >= P.n {
        return;
    }
    let l = i ^ P.b;
    if l > i {
        let a = keys[i];
        let b = keys[l];
        let up = (i & P.a) == 0u;
        if key_less(b, a) == up {
            keys[i] = b;
            keys[l] = a;
        }
    }
}

// Kernel `sort_local`: the bitonic sort's steps whose pairs lie inside one
// block of 512 keys, done in workgroup memory (one dispatch instead of one
// per step; `sort` does the steps with j >= 512 in global memory). A
// workgroup of 256 threads owns keys[512 w .. 512 w + 512); each step, each
// thread compares one pair (i, i + j), the direction given by the global
// index as in `sort`. P.n: the padded key count (a multiple of 512);
// P.a = 0: all steps k = 2 .. 512 (sorts each block); P.a = k >= 1024: the
// steps j = 256 .. 1 of that k.

@group(0) @binding(0) var<uniform> P: Small;
@group(0) @binding(1) var<storage, read_write> keys: array<vec4<u32>>;

const BLOCK: u32 = 512u;
var<workgroup> sk: array<vec4<u32>, BLOCK>;

fn step(base: u32, t: u32, k: u32, j: u32) {
    let i = 2u * j * (t / j) + t % j;
    let l = i + j;
    let a = sk[i];
    let b = sk[l];
    let up = ((base + i) & k) == 0u;
    if key_less(b, a) == up {
        sk[i] = b;
        sk[l] = a;
    }
    workgroupBarrier();
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) t: u32) {
    let w = wid.x + wid.y * nwg.x;
    let base = w * BLOCK;
    if base >= P.n {
        return;
    }
    sk[t] = keys[base + t];
    sk[t + 256u] = keys[base + t + 256u];
    workgroupBarrier();
    if P.a == 0u {
        for (var k = 2u; k <= BLOCK; k *= 2u) {
            for (var j = k / 2u; j > 0u; j /= 2u) {
                step(base, t, k, j);
            }
        }
    } else {
        for (var j = BLOCK / 2u; j > 0u; j /= 2u) {
            step(base, t, P.a, j);
        }
    }
    keys[base + t] = sk[t];
    keys[base + t + 256u] = sk[t + 256u];
}

// Frame preprocessing on packed 8-bit frames (4 pixels per u32 word, little-endian: pixel x is
// byte x % 4 of word x / 4; rows padded to `ws` words). Bit-identical to
// `flow::prefilter::{downsample, highpass}` (docs/flow.md contract §2 and §3).

// `Lv`, `lv` (binding 0) and `unpack` come from common.wgsl, which the Rust side prepends.
@group(0) @binding(1) var<storage, read> src: array<u32>;
@group(0) @binding(2) var<storage, read_write> cs_out: array<u32>;
@group(0) @binding(3) var<storage, read> cs_in: array<u32>;
@group(0) @binding(4) var<storage, read_write> dst: array<u32>;

fn pack(v: vec4<u32>) -> u32 {
    return v.x | (v.y << 8u) | (v.z << 16u) | (v.w << 24u);
}

// Pass 1 of the high-pass: column sums S_col(x, y) = sum of I(x, clamp(y + j)) for |j| <= k.
// One invocation per word (4 pixels).
@compute @workgroup_size(64, 1, 1)
fn colsum(@builtin(global_invocation_id) gid: vec3<u32>) {
    let x4 = gid.x;
    let y = gid.y;
    if x4 >= lv.ws || y >= lv.h {
        return;
    }
    var s = vec4<u32>(0u);
    let k = i32(lv.k);
    for (var j = -k; j <= k; j++) {
        let yy = u32(clamp(i32(y) + j, 0, i32(lv.h) - 1));
        s += unpack(src[yy * lv.ws + x4]);
    }
    for (var i = 0u; i < 4u; i++) {
        let x = 4u * x4 + i;
        if x < lv.w {
            cs_out[y * lv.w + x] = s[i];
        }
    }
}

fn cs_at(y: u32, x: i32) -> u32 {
    return cs_in[y * lv.w + u32(clamp(x, 0, i32(lv.w) - 1))];
}

// Pass 2: hp = clamp(128 + I - (S + (n - 1) / 2) / n, 0, 255) with S the horizontal sum of the
// column sums over |i| <= k (edge-replicated), a sliding sum over the word's 4 pixels.
@compute @workgroup_size(64, 1, 1)
fn highpass(@builtin(global_invocation_id) gid: vec3<u32>) {
    let x4 = gid.x;
    let y = gid.y;
    if x4 >= lv.ws || y >= lv.h {
        return;
    }
    let k = i32(lv.k);
    let x0 = i32(4u * x4);
    var s = 0u;
    for (var i = -k; i <= k; i++) {
        s += cs_at(y, x0 + i);
    }
    let px = unpack(src[y * lv.ws + x4]);
    var out = vec4<u32>(0u);
    for (var i = 0; i < 4; i++) {
        if i > 0 {
            s = s + cs_at(y, x0 + i + k) - cs_at(y, x0 + i - 1 - k);
        }
        if u32(x0 + i) < lv.w {
            let mean = (s + (lv.n - 1u) / 2u) / lv.n;
            out[i] = u32(clamp(128 + i32(px[i]) - i32(mean), 0, 255));
        }
    }
    dst[y * lv.ws + x4] = pack(out);
}

// 2x2 average into the next pyramid level: (s00 + s10 + s01 + s11 + 2) >> 2. `lv` describes the
// destination level; `ws_src` is the source row length in words.
@compute @workgroup_size(64, 1, 1)
fn downsample(@builtin(global_invocation_id) gid: vec3<u32>) {
    let x4 = gid.x;
    let y = gid.y;
    if x4 >= lv.ws || y >= lv.h {
        return;
    }
    let r0 = 2u * y * lv.ws_src;
    let r1 = r0 + lv.ws_src;
    var out = vec4<u32>(0u);
    for (var i = 0u; i < 2u; i++) {
        let wi = 2u * x4 + i;
        if wi < lv.ws_src {
            let a = unpack(src[r0 + wi]);
            let b = unpack(src[r1 + wi]);
            out[2u * i] = (a.x + a.y + b.x + b.y + 2u) >> 2u;
            out[2u * i + 1u] = (a.z + a.w + b.z + b.w + 2u) >> 2u;
        }
    }
    for (var i = 0u; i < 4u; i++) {
        if 4u * x4 + i >= lv.w {
            out[i] = 0u;
        }
    }
    dst[y * lv.ws + x4] = pack(out);
}

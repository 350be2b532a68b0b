// Shared by prep.wgsl, match.wgsl and costvol.wgsl; the Rust side (src/flow/gpu.rs) prepends
// it to each. WGSL has no include.

// One pyramid level's dimensions and parameters: `LevelUniform` in src/flow/gpu.rs, field for
// field.
struct Lv {
    w: u32, h: u32, ws: u32, ws_src: u32,
    k: u32, n: u32, rows: u32, cols: u32,
    coarsest: u32, radius: u32, q: u32, level: u32,
}

@group(0) @binding(0) var<uniform> lv: Lv;

// The 4 pixels of a packed word (pixel x is byte x % 4 of word x / 4, little-endian).
fn unpack(w: u32) -> vec4<u32> {
    return vec4<u32>(w & 255u, (w >> 8u) & 255u, (w >> 16u) & 255u, w >> 24u);
}

// Four pixels starting `sh` bits into `lo`, the rest from the next word `hi` (sh in 0, 8, 16,
// 24). `hi` is shifted by 32 - sh in two steps so that sh = 0 takes nothing from it (a shift
// by 32 would keep it whole): no branch, one expression for every alignment.
fn funnel4(lo: u32, hi: u32, sh: u32) -> u32 {
    return (lo >> sh) | ((hi << 1u) << (31u - sh));
}

// Dense single-level fast path, kernel A: the cost volume (docs/gpu.md, "Dense mode").
//
// Blocks overlap (at stride 8 with 32 px blocks every pixel lies in 16 blocks), so the
// per-pixel absolute differences |A(p) − B(p + d)| are shared: a workgroup takes a tile of
// TC × TR blocks and one candidate row dy (workgroup_id = (tile column, tile row, dy + R)),
// and for groups of G candidate columns dx:
//   phase 1: each invocation owns one dx and 4 adjacent pixel columns of the tile's region
//            (one packed word of A and of B per row, read with funnel shifts; which words
//            exist is decided once per walk, per row only B's row is checked) and walks down
//            the region's rows once, keeping the running column sum S(y) of the differences;
//            at each block row's first row it stores S, at its end row it stores S − stored,
//            i.e. the column sum over that block row's BL rows: V[r][x][dx] (workgroup memory,
//            dx fastest; each entry written and re-read only by the invocation that owns it);
//            with QS (every block starts a multiple of 4 columns after the region's start and
//            BL is a multiple of 4) V keeps one word per quad of 4 columns, their sum, x = xq/4,
//            so V takes a quarter of the memory (more workgroups per multiprocessor);
//   barrier;
//   phase 2: each invocation sums BL consecutive V columns (BL/4 quads with QS) into one
//            block's cost at (dx, dy)
//            (consecutive invocations: consecutive dx of one block) and writes it into the
//            block's cost grid (the layout match.wgsl uses with global
//            costs: bi·ND² + (dy − lo.y)·nx + (dx − lo.x)) when d is in the block's window;
//   barrier (V is overwritten by the next group).
// Integer sums, so the costs equal the CPU engine's SADs exactly. Every buffer and array index
// is bounds-checked; pixels of B outside the frame read as 0 explicitly, and only enter
// candidates outside the block's window, which are never written. Barriers are in uniform
// control flow only (their loops depend on constants and workgroup-uniform values).
//
// The Rust side prepends: WG, BL (block side), R (radius), ND (2R+1), TC, TR (tile), G (dx per
// group), RWM (widest tile region, px), RWQ (= ⌈RWM/4⌉), QS, VW (V words per block row and dx:
// RWQ with QS, else RWM), VSN (= G·VW·TR), CST/RST (tile-table strides),
// ROWBASE (offset of the row-tile table), SWAR (with QS, a row's 4 differences taken and
// summed in place, `row_cost`; docs/gpu.md), DQ (with QS, walks of 4 dx, `walk_dx_quads`).
//
// Tile table `tiles` (u32): column tile tc at tc·CST: [X0, region width, valid columns];
// row tile tr at ROWBASE + tr·RST: [Y0, region height, valid rows, n events, events...], each
// event (y << 12) | (r << 1) | end, sorted by y: block row r of the tile starts (end = 0) or
// ends (end = 1) before region row y.

// `Lv`, `lv` (binding 0) and `unpack` come from common.wgsl, which the Rust side prepends.
@group(0) @binding(1) var<storage, read> hpa: array<u32>;
@group(0) @binding(2) var<storage, read> hpb: array<u32>;
@group(0) @binding(3) var<storage, read> orig: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> tiles: array<u32>;
@group(0) @binding(5) var<storage, read_write> gcost: array<u32>;

var<workgroup> vs: array<u32, VSN>;

fn tile(i: u32) -> u32 {
    if i < arrayLength(&tiles) {
        return tiles[i];
    }
    return 0u;
}

// Word `i` of frame A or B, 0 past the end of the buffer (never read: the callers check the
// row and the word column first; this keeps every access explicitly in bounds).
// The 4 pixels starting `sh` bits into the word pair (lo, hi); sh is a multiple of 8.
fn funnel(lo: u32, hi: u32, sh: u32) -> u32 {
    if sh == 0u {
        return lo;
    }
    return (lo >> sh) | (hi << (32u - sh));
}

fn word_a(i: u32) -> u32 {
    if i < arrayLength(&hpa) {
        return hpa[i];
    }
    return 0u;
}

fn word_b(i: u32) -> u32 {
    if i < arrayLength(&hpb) {
        return hpb[i];
    }
    return 0u;
}

// Where a walk's 4 columns starting at pixel `ax` lie in frame A's rows: the word column, the
// shift into it, and which of the two words read exist (inside the row's words).
struct ACol {
    wx: u32,
    sh: u32,
    lo: bool,
    hi: bool,
}

fn a_col(ax: u32) -> ACol {
    let wx = ax >> 2u;
    let sh = (ax & 3u) * 8u;
    return ACol(wx, sh, wx < lv.ws, sh != 0u && wx + 1u < lv.ws);
}

// The walk's 4 pixels of A in row `ay` (0 below the frame).
fn a_row_word(c: ACol, ay: u32) -> u32 {
    var lo = 0u;
    var hi = 0u;
    if ay < lv.h {
        let i = ay * lv.ws + c.wx;
        if c.lo {
            lo = word_a(i);
        }
        if c.hi {
            hi = word_a(i + 1u);
        }
    }
    return funnel(lo, hi, c.sh);
}

// Word column `wx` of B's row `by` where `ok` (the column lies inside the row's words), else
// 0, as outside the frame.
fn b_word(by: i32, wx: i32, ok: bool) -> u32 {
    if ok && by >= 0 && by < i32(lv.h) {
        return word_b(u32(by * i32(lv.ws) + wx));
    }
    return 0u;
}

// |a − b| of each of the 4 bytes of two packed words, in place (SIMD within the register):
// bit 7 of `ge` says a ≥ b per byte, from the top bits and a borrow-free subtraction of the low
// seven; then max − min per byte, which cannot borrow across bytes.
fn absdiff_bytes(a: u32, b: u32) -> u32 {
    let h = 0x80808080u;
    let t = (a | h) - (b & ~h);
    let x = a ^ b;
    let ge = ((a & ~b) | (~x & t)) & h;
    let m = (ge - (ge >> 7u)) | ge;
    let xm = x & m;
    return (b ^ xm) - (a ^ xm);
}

// One row's absolute differences for the 4 columns of a walk (`aw`, `bw`: A's and B's words).
// With quad sums (QS) only their total is used: with SWAR the 4 differences are taken in place
// and added by a packed dot product (one instruction where the GPU has it), the total in x;
// otherwise the 4 columns are unpacked.
fn row_cost(aw: u32, bw: u32) -> vec4<u32> {
    if QS && SWAR {
        return vec4<u32>(dot4U8Packed(absdiff_bytes(aw, bw), 0x01010101u), 0u, 0u, 0u);
    }
    let a = unpack(aw);
    let b = unpack(bw);
    return max(a, b) - min(a, b);
}

// Phase 1 with quads of dx (DQ; QS holds): each invocation takes 4 adjacent columns and the 4
// consecutive dx from g0 + 4·gq. Per row, one word of A (`a_row_word`) and
// the 3 words of B that hold the 7 pixels the 4 shifts need: t0 and t1 are B's 8 pixels from
// the first dx's column, and the k-th dx reads the 4 of them from byte k, by constant shifts.
// A dx past the group (G) or the window (ND) is walked but not stored.
fn walk_dx_quads(g0: u32, x0t: u32, rw: u32, y0t: u32, rb: u32, rh: u32, nev: u32, dy: i32, tid: u32) {
    let ones = 0x01010101u;
    for (var it = tid; it < ((G + 3u) / 4u) * RWQ; it += WG) {
        let gq = it / RWQ;
        let xq = 4u * (it - gq * RWQ);
        let dx0 = g0 + 4u * gq;
        if xq >= rw || dx0 >= ND {
            continue;
        }
        let ax = x0t + xq;
        let ac = a_col(ax);
        let bx = i32(ax) + i32(dx0) - i32(R);
        let ws = i32(lv.ws);
        let bwx = bx >> 2u;
        let bsh = u32(bx & 3) * 8u;
        let b0 = bwx >= 0 && bwx < ws;
        let b1 = bwx + 1 >= 0 && bwx + 1 < ws;
        let b2 = bwx + 2 >= 0 && bwx + 2 < ws;
        var s = vec4<u32>(0u);
        var y = 0u;
        for (var e = 0u; e < nev; e++) {
            let ev = tile(rb + 4u + e);
            let ye = min(ev >> 12u, rh);
            while y < ye {
                let ay = y0t + y;
                let aw = a_row_word(ac, ay);
                let by = i32(ay) + dy;
                let w0 = b_word(by, bwx, b0);
                let w1 = b_word(by, bwx + 1, b1);
                let w2 = b_word(by, bwx + 2, b2);
                let t0 = funnel4(w0, w1, bsh);
                let t1 = funnel4(w1, w2, bsh);
                s.x += dot4U8Packed(absdiff_bytes(aw, t0), ones);
                s.y += dot4U8Packed(absdiff_bytes(aw, (t0 >> 8u) | (t1 << 24u)), ones);
                s.z += dot4U8Packed(absdiff_bytes(aw, (t0 >> 16u) | (t1 << 16u)), ones);
                s.w += dot4U8Packed(absdiff_bytes(aw, (t0 >> 24u) | (t1 << 8u)), ones);
                y++;
            }
            let r = (ev >> 1u) & 2047u;
            let g = 4u * gq;
            let i = (r * VW + (xq >> 2u)) * G + g;
            let ok = r < TR;
            put_v(i, ok, ev, s.x);
            put_v(i + 1u, ok && g + 1u < G && dx0 + 1u < ND, ev, s.y);
            put_v(i + 2u, ok && g + 2u < G && dx0 + 2u < ND, ev, s.z);
            put_v(i + 3u, ok && g + 3u < G && dx0 + 3u < ND, ev, s.w);
        }
    }
}

// One column sum of V at index i (a block row's first row stores the running sum, its end
// row the difference), where the dx exists (`ok`).
fn put_v(i: u32, ok: bool, ev: u32, v: u32) {
    if ok && i < VSN {
        if (ev & 1u) == 0u {
            vs[i] = v;
        } else {
            vs[i] = v - vs[i];
        }
    }
}

@compute @workgroup_size(WG, 1, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) tid: u32) {
    let cb = wid.x * CST;
    let rb = ROWBASE + wid.y * RST;
    let dy = i32(wid.z) - i32(R);
    let x0t = tile(cb);
    let rw = min(tile(cb + 1u), RWM);
    let ncv = min(tile(cb + 2u), TC);
    let y0t = tile(rb);
    let rh = tile(rb + 1u);
    let nrv = min(tile(rb + 2u), TR);
    let nev = min(tile(rb + 3u), 2u * TR);
    let ngroups = (ND + G - 1u) / G;

    for (var grp = 0u; grp < ngroups; grp++) {
        let g0 = grp * G;
        // Phase 1: column sums of |A − B(· + d)| over each block row, per (dx, column); each
        // invocation takes 4 adjacent columns (one packed word of each frame per row). The
        // word columns and their validity are fixed per walk; per row only B's row is checked.
        if DQ {
            walk_dx_quads(g0, x0t, rw, y0t, rb, rh, nev, dy, tid);
        }
        for (var it = tid; it < select(G * RWQ, 0u, DQ); it += WG) {
            let g = it / RWQ;
            let xq = 4u * (it - g * RWQ);
            let dxi = g0 + g;
            if xq < rw && dxi < ND {
                let ax = x0t + xq;
                let ac = a_col(ax);
                let bx = i32(ax) + i32(dxi) - i32(R);
                let ws = i32(lv.ws);
                let bwx = bx >> 2u;
                let bsh = u32(bx & 3) * 8u;
                let b0 = bwx >= 0 && bwx < ws;
                let b1 = bsh != 0u && bwx + 1 >= 0 && bwx + 1 < ws;
                var s = vec4<u32>(0u);
                var y = 0u;
                for (var e = 0u; e < nev; e++) {
                    let ev = tile(rb + 4u + e);
                    let ye = min(ev >> 12u, rh);
                    while y < ye {
                        let ay = y0t + y;
                        let aw = a_row_word(ac, ay);
                        let by = i32(ay) + dy;
                        let bw = funnel(b_word(by, bwx, b0), b_word(by, bwx + 1, b1), bsh);
                        s += row_cost(aw, bw);
                        y++;
                    }
                    let r = (ev >> 1u) & 2047u;
                    if QS {
                        // one word per quad: the sum of the 4 columns
                        let k = (r * VW + (xq >> 2u)) * G + g;
                        let sq = s.x + s.y + s.z + s.w;
                        if r < TR && k < VSN {
                            if (ev & 1u) == 0u {
                                vs[k] = sq;
                            } else {
                                vs[k] = sq - vs[k];
                            }
                        }
                    } else {
                        for (var i = 0u; i < 4u; i++) {
                            let xl = xq + i;
                            let k = (r * VW + xl) * G + g;
                            if r < TR && xl < rw && k < VSN {
                                if (ev & 1u) == 0u {
                                    vs[k] = s[i];
                                } else {
                                    vs[k] = s[i] - vs[k];
                                }
                            }
                        }
                    }
                }
            }
        }
        workgroupBarrier();
        // Phase 2: block costs = sums of BL consecutive column sums.
        // Consecutive invocations take consecutive dx of one block: conflict-free reads of V
        // (dx fastest) and contiguous writes into the block's cost grid.
        for (var it = tid; it < G * TR * TC; it += WG) {
            let rem = it / G;
            let g = it - rem * G;
            let r = rem / TC;
            let c = rem - r * TC;
            let dxi = g0 + g;
            if dxi < ND && r < nrv && c < ncv {
                let row = wid.y * TR + r;
                let col = wid.x * TC + c;
                let bi = row * lv.cols + col;
                if row < lv.rows && col < lv.cols && bi < arrayLength(&orig) {
                    let o = orig[bi];
                    let dx = i32(dxi) - i32(R);
                    let x0 = i32(o.x);
                    let y0 = i32(o.y);
                    let bl = i32(BL);
                    // The block's window, exactly as match.wgsl and the CPU engine cut it.
                    let fmin = vec2<i32>(-x0, -y0);
                    let fmax = vec2<i32>(i32(lv.w) - bl - x0, i32(lv.h) - bl - y0);
                    let p = clamp(vec2<i32>(0, 0), fmin, fmax);
                    let rad = i32(R);
                    let lo = max(p - vec2<i32>(rad), fmin);
                    let hi = min(p + vec2<i32>(rad), fmax);
                    let xl = o.x - x0t;
                    if dx >= lo.x && dx <= hi.x && dy >= lo.y && dy <= hi.y && o.x >= x0t && xl + BL <= rw {
                        var s = 0u;
                        if QS {
                            // xl and BL are multiples of 4 (planned so): BL / 4 quad sums
                            let vb = (r * VW + (xl >> 2u)) * G + g;
                            for (var i = 0u; i < BL / 4u; i++) {
                                let k = vb + i * G;
                                if k < VSN {
                                    s += vs[k];
                                }
                            }
                        } else {
                            let vb = (r * VW + xl) * G + g;
                            for (var i = 0u; i < BL; i++) {
                                let k = vb + i * G;
                                if k < VSN {
                                    s += vs[k];
                                }
                            }
                        }
                        let nx = u32(hi.x - lo.x + 1);
                        let j = u32(dy - lo.y) * nx + u32(dx - lo.x);
                        let gi = bi * ND * ND + j;
                        if gi < arrayLength(&gcost) {
                            gcost[gi] = s;
                        }
                    }
                }
            }
        }
        workgroupBarrier();
    }
}

// Block matching, one workgroup per block and pyramid level (docs/flow.md contract §4–§9).
// The Rust side prepends the constants (block side BL, window size NXM×NYM, band TY, chunk CH,
// ...). Candidates are processed in bands of TY candidate rows; the block rows in chunks of CH.
// For each (band, chunk) the rows of the reference block (A) and the part of the search window
// of B that the band needs are cached in workgroup memory; each invocation accumulates the full
// SAD of its PER candidates. Costs are exact integers; the best candidate and the ambiguity
// flag come from workgroup reductions, so the result equals the exhaustive CPU search.
// With PRE (the dense single-level fast path) the SAD loop is skipped: the costs were computed
// by costvol.wgsl into gcost, in the same layout, and only the reductions run here; they are
// read from global memory once, into workgroup memory (COSTS_WG) when it fits. With PCACHE the
// texture energy and SSDs read the block of A and the (BL + 2)² patch of B around d1 from
// workgroup memory (one pixel per word, loaded once) instead of global memory.

// `Lv`, `lv` (binding 0), `unpack` and `funnel4` come from common.wgsl, which the Rust side prepends.
@group(0) @binding(1) var<storage, read> hpa: array<u32>;
@group(0) @binding(2) var<storage, read> hpb: array<u32>;
@group(0) @binding(3) var<storage, read> orig: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> dprev: array<vec2<i32>>;
@group(0) @binding(5) var<storage, read_write> dout: array<vec2<i32>>;
@group(0) @binding(6) var<storage, read_write> flags: array<u32>;
@group(0) @binding(7) var<storage, read_write> res: array<u32>;
@group(0) @binding(8) var<storage, read_write> gcost: array<u32>;

const RECORD: u32 = 10u;

var<workgroup> sa: array<u32, SAN>;
var<workgroup> sb: array<u32, SBN>;
var<workgroup> wcost: array<u32, WCN>;
var<workgroup> red_cost: atomic<u32>;
var<workgroup> red_key: atomic<u32>;
var<workgroup> red_amb: atomic<u32>;
var<workgroup> red_sum: array<atomic<u32>, 6>;

fn sad4(a: u32, b: u32) -> u32 {
    let ua = unpack(a);
    let ub = unpack(b);
    let d = max(ua, ub) - min(ua, ub);
    return d.x + d.y + d.z + d.w;
}

// SAD of the two low pixels only (block rows whose length is 2 mod 4).
fn sad2(a: u32, b: u32) -> u32 {
    let ua = unpack(a);
    let ub = unpack(b);
    let d = max(ua, ub) - min(ua, ub);
    return d.x + d.y;
}

// Four pixels of a frame starting at pixel (x, y), any alignment.
fn frame_word_a(x: u32, y: u32) -> u32 {
    let i = y * lv.ws + (x >> 2u);
    let s = (x & 3u) * 8u;
    let lo = hpa[i];
    if s == 0u {
        return lo;
    }
    var hi = 0u;
    if i + 1u < arrayLength(&hpa) {
        hi = hpa[i + 1u];
    }
    return (lo >> s) | (hi << (32u - s));
}

fn word_b(i: u32) -> u32 {
    if i < arrayLength(&hpb) {
        return hpb[i];
    }
    return 0u;
}

fn pix_a(x: u32, y: u32) -> u32 {
    return (hpa[y * lv.ws + (x >> 2u)] >> ((x & 3u) * 8u)) & 255u;
}

fn pix_b(x: u32, y: u32) -> u32 {
    return (hpb[y * lv.ws + (x >> 2u)] >> ((x & 3u) * 8u)) & 255u;
}

fn cost_set(base: u32, j: u32, c: u32) {
    if COSTS_WG {
        wcost[j] = c;
    } else {
        gcost[base + j] = c;
    }
}

// A cost written by costvol.wgsl (PRE), read from global memory.
fn cost_pre(base: u32, j: u32) -> u32 {
    if base + j < arrayLength(&gcost) {
        return gcost[base + j];
    }
    return 0xffffffffu;
}

fn cost_get(base: u32, j: u32) -> u32 {
    if COSTS_WG {
        return wcost[j];
    }
    if base + j < arrayLength(&gcost) {
        return gcost[base + j];
    }
    return 0xffffffffu;
}

// Lower median (index (n - 1) / 2) of the first n values.
fn lower_median(v: array<i32, 9>, n: u32) -> i32 {
    var a = v;
    for (var i = 1u; i < n; i++) {
        let x = a[i];
        var j = i;
        while j > 0u && a[j - 1u] > x {
            a[j] = a[j - 1u];
            j--;
        }
        a[j] = x;
    }
    return a[(n - 1u) / 2u];
}

@compute @workgroup_size(WG, 1, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) tid: u32) {
    let cols = lv.cols;
    let rows = lv.rows;
    let bi = wid.y * cols + wid.x;
    let o = orig[bi];
    let x0 = i32(o.x);
    let y0 = i32(o.y);
    let bl = i32(BL);

    // Window centre: (0, 0) at the coarsest level, else twice the lower median of the 3×3
    // neighbourhood's displacements at the coarser level. Every invocation computes the same.
    var centre = vec2<i32>(0, 0);
    if lv.coarsest == 0u {
        var xs: array<i32, 9>;
        var ys: array<i32, 9>;
        var n = 0u;
        let r0 = select(wid.y - 1u, 0u, wid.y == 0u);
        let c0 = select(wid.x - 1u, 0u, wid.x == 0u);
        let r1 = min(wid.y + 1u, rows - 1u);
        let c1 = min(wid.x + 1u, cols - 1u);
        for (var r = r0; r <= r1; r++) {
            for (var c = c0; c <= c1; c++) {
                let d = dprev[r * cols + c];
                xs[n] = d.x;
                ys[n] = d.y;
                n++;
            }
        }
        centre = 2 * vec2<i32>(lower_median(xs, n), lower_median(ys, n));
    }
    let fmin = vec2<i32>(-x0, -y0);
    let fmax = vec2<i32>(i32(lv.w) - bl - x0, i32(lv.h) - bl - y0);
    let p = clamp(centre, fmin, fmax);
    let rad = i32(lv.radius);
    let lo = max(p - vec2<i32>(rad), fmin);
    let hi = min(p + vec2<i32>(rad), fmax);
    let nx = u32(hi.x - lo.x + 1);
    let ny = u32(hi.y - lo.y + 1);
    let gbase = bi * NXM * NYM;
    // Window origin in frame B (top-left pixel of the block at displacement lo).
    let wx = u32(x0 + lo.x);
    let wy = u32(y0 + lo.y);
    let off0 = wx & 3u;
    let wx_word = wx >> 2u;

    if tid == 0u {
        atomicStore(&red_cost, 0xffffffffu);
        atomicStore(&red_key, 0xffffffffu);
        atomicStore(&red_amb, 0u);
        for (var i = 0u; i < 6u; i++) {
            atomicStore(&red_sum[i], 0u);
        }
    }

    var best_c = 0xffffffffu;
    var best_k = 0xffffffffu;
    if PRE {
        // Dense fast path: costvol.wgsl has written every candidate's cost into gcost (a
        // previous dispatch). Order the atomics' initialisation above before their use below.
        workgroupBarrier();
        for (var j = tid; j < nx * ny; j += WG) {
            let cy = j / nx;
            let cx = j - cy * nx;
            let c = cost_pre(gbase, j);
            if COSTS_WG {
                wcost[j] = c;
            }
            let e = vec2<i32>(lo.x + i32(cx), lo.y + i32(cy)) - p;
            let key = (u32(e.x * e.x + e.y * e.y) << 16u) | (cy << 8u) | cx;
            if c < best_c || (c == best_c && key < best_k) {
                best_c = c;
                best_k = key;
            }
        }
    }
    let nbands = select((ny + TY - 1u) / TY, 0u, PRE);
    for (var band = 0u; band < nbands; band++) {
        let ty0 = band * TY;
        let tyb = min(TY, ny - ty0);
        let nband = nx * tyb;
        var acc: array<u32, PER>;
        for (var kk = 0u; kk < PER; kk++) {
            acc[kk] = 0u;
        }
        for (var ch = 0u; ch < NCH; ch++) {
            let cy0 = ch * CH;
            let chn = min(CH, BL - cy0);
            workgroupBarrier();
            // Reference block rows [cy0, cy0 + chn) of A.
            for (var i = tid; i < chn * AW; i += WG) {
                let r = i / AW;
                let j = i - r * AW;
                sa[i] = frame_word_a(u32(x0) + 4u * j, u32(y0) + cy0 + r);
            }
            // Window rows of B for candidate rows [ty0, ty0 + tyb) and block rows of the chunk.
            let sbrows = chn + tyb - 1u;
            for (var i = tid; i < sbrows * RW; i += WG) {
                let r = i / RW;
                let j = i - r * RW;
                sb[i] = word_b((wy + ty0 + cy0 + r) * lv.ws + wx_word + j);
            }
            workgroupBarrier();
            for (var kk = 0u; kk < PER; kk++) {
                let j = tid + kk * WG;
                if j < nband {
                    let cy = j / nx;
                    let cx = j - cy * nx;
                    var s = acc[kk];
                    // The candidate's window row starts `sh` bits into word `col` of each cached
                    // row; walking along the row, each word of B is loaded once and serves as the
                    // high part of one step and the low part of the next. The last word read,
                    // col + AW at most, lies inside the row's RW words.
                    let pp = off0 + cx;
                    let sh = (pp & 3u) * 8u;
                    let col = pp >> 2u;
                    for (var r = 0u; r < chn; r++) {
                        let arow = r * AW;
                        var bi = (r + cy) * RW + col;
                        var lo = sb[bi];
                        for (var wi = 0u; wi < AWF; wi++) {
                            bi += 1u;
                            let hi = sb[bi];
                            s += sad4(sa[arow + wi], funnel4(lo, hi, sh));
                            lo = hi;
                        }
                        if TAIL {
                            s += sad2(sa[arow + AWF], funnel4(lo, sb[bi + 1u], sh));
                        }
                    }
                    acc[kk] = s;
                }
            }
        }
        for (var kk = 0u; kk < PER; kk++) {
            let j = tid + kk * WG;
            if j < nband {
                let cy = j / nx;
                let cx = j - cy * nx;
                let gy = ty0 + cy;
                let c = acc[kk];
                cost_set(gbase, gy * nx + cx, c);
                let e = vec2<i32>(lo.x + i32(cx), lo.y + i32(gy)) - p;
                let key = (u32(e.x * e.x + e.y * e.y) << 16u) | (gy << 8u) | cx;
                if c < best_c || (c == best_c && key < best_k) {
                    best_c = c;
                    best_k = key;
                }
            }
        }
    }

    // Best candidate: smallest cost, then the tie-break key (distance², dy, dx).
    atomicMin(&red_cost, best_c);
    storageBarrier();
    workgroupBarrier();
    let c1 = atomicLoad(&red_cost);
    if best_c == c1 {
        atomicMin(&red_key, best_k);
    }
    workgroupBarrier();
    let key1 = atomicLoad(&red_key);
    let b = vec2<u32>(key1 & 255u, (key1 >> 8u) & 255u);
    let d1 = lo + vec2<i32>(b);
    let edge = d1.x == lo.x || d1.x == hi.x || d1.y == lo.y || d1.y == hi.y;

    // Ambiguity: a local minimum at Chebyshev distance >= 2 with 256·C <= c1·(256 + q), i.e.
    // C <= c1 + floor(c1·q / 256), computed without overflowing 32 bits.
    let thr = c1 + (c1 >> 8u) * lv.q + (((c1 & 255u) * lv.q) >> 8u);
    for (var j = tid; j < nx * ny; j += WG) {
        let c = cost_get(gbase, j);
        if c > thr {
            continue;
        }
        let cy = j / nx;
        let cx = j - cy * nx;
        if max(abs(i32(cx) - i32(b.x)), abs(i32(cy) - i32(b.y))) < 2 {
            continue;
        }
        var is_min = true;
        for (var dy = -1; dy <= 1; dy++) {
            for (var dx = -1; dx <= 1; dx++) {
                let ex = i32(cx) + dx;
                let ey = i32(cy) + dy;
                if ex >= 0 && ey >= 0 && ex < i32(nx) && ey < i32(ny) {
                    if cost_get(gbase, u32(ey) * nx + u32(ex)) < c {
                        is_min = false;
                    }
                }
            }
        }
        if is_min {
            atomicOr(&red_amb, 1u);
        }
    }

    // Level 0: texture energy of the block and the SSD at d1 and its 4 neighbours.
    let in_xm = d1.x > lo.x;
    let in_xp = d1.x < hi.x;
    let in_ym = d1.y > lo.y;
    let in_yp = d1.y < hi.y;
    if IS_L0 {
        if PCACHE {
            // The block of A (BL × BL) and the patch of B around d1 ((BL + 2)², covering the
            // four neighbours) into workgroup memory, one pixel per word; patch pixels outside
            // the frame (only next to a window cut by the frame, never used) read as 0.
            for (var i = tid; i < BL * BL; i += WG) {
                let y = i / BL;
                let x = i - y * BL;
                sa[i] = pix_a(u32(x0) + x, u32(y0) + y);
            }
            for (var i = tid; i < PW * PW; i += WG) {
                let y = i / PW;
                let x = i - y * PW;
                let bx = x0 + d1.x - 1 + i32(x);
                let by = y0 + d1.y - 1 + i32(y);
                var v = 0u;
                if bx >= 0 && by >= 0 && bx < i32(lv.w) && by < i32(lv.h) {
                    v = pix_b(u32(bx), u32(by));
                }
                sb[i] = v;
            }
            workgroupBarrier();
        }
        var g = 0u;
        var s = array<u32, 5>(0u, 0u, 0u, 0u, 0u);
        var offs = array<vec2<i32>, 5>(vec2<i32>(0, 0), vec2<i32>(-1, 0), vec2<i32>(1, 0), vec2<i32>(0, -1), vec2<i32>(0, 1));
        var use_n = array<bool, 5>(true, in_xm, in_xp, in_ym, in_yp);
        for (var i = tid; i < BL * BL; i += WG) {
            let y = i / BL;
            let x = i - y * BL;
            let ax = u32(x0) + x;
            let ay = u32(y0) + y;
            if PCACHE {
                let a = sa[i];
                if x + 1u < BL {
                    let q = sa[i + 1u];
                    g += max(a, q) - min(a, q);
                }
                if y + 1u < BL {
                    let q = sa[i + BL];
                    g += max(a, q) - min(a, q);
                }
                for (var m = 0u; m < 5u; m++) {
                    if use_n[m] {
                        let o = offs[m];
                        let q = sb[u32(i32((y + 1u) * PW + x + 1u) + o.y * i32(PW) + o.x)];
                        let diff = max(a, q) - min(a, q);
                        s[m] += diff * diff;
                    }
                }
                continue;
            }
            let a = pix_a(ax, ay);
            if x + 1u < BL {
                let q = pix_a(ax + 1u, ay);
                g += max(a, q) - min(a, q);
            }
            if y + 1u < BL {
                let q = pix_a(ax, ay + 1u);
                g += max(a, q) - min(a, q);
            }
            for (var m = 0u; m < 5u; m++) {
                if use_n[m] {
                    let d = d1 + offs[m];
                    let q = pix_b(u32(i32(ax) + d.x), u32(i32(ay) + d.y));
                    let diff = max(a, q) - min(a, q);
                    s[m] += diff * diff;
                }
            }
        }
        for (var m = 0u; m < 5u; m++) {
            atomicAdd(&red_sum[m], s[m]);
        }
        atomicAdd(&red_sum[5], g);
    }
    workgroupBarrier();

    if tid == 0u {
        dout[bi] = d1;
        var f = 0u;
        if lv.coarsest == 0u {
            f = flags[bi];
        }
        f |= select(0u, 1u, edge) | select(0u, 2u, atomicLoad(&red_amb) != 0u);
        flags[bi] = f;
        if IS_L0 {
            let rb = bi * RECORD;
            res[rb + 0u] = bitcast<u32>(d1.x);
            res[rb + 1u] = bitcast<u32>(d1.y);
            res[rb + 2u] = c1;
            res[rb + 3u] = f | select(0u, 4u, in_xm) | select(0u, 8u, in_xp) | select(0u, 16u, in_ym) | select(0u, 32u, in_yp);
            for (var m = 0u; m < 6u; m++) {
                res[rb + 4u + m] = atomicLoad(&red_sum[m]);
            }
        }
    }
}

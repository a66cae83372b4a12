// The compositing forward and backward passes of the compiled CPU rasterizer in C++ (issue 31 item 1, round
// raster24): the same contract, arrays and arithmetic as cpu_kernels.composite_forward / composite_backward
// (read their docstrings for the maths; models/gaussians/README.md "Rendering"), written from that maths. Built by
// cpu_ext.py with g++ into a plain shared library called through ctypes (no torch headers: it builds in seconds).
//
// What differs from the numba kernels: the exp of pass 2 is an inlined polynomial the compiler vectorises (8 float32
// lanes with AVX2), and the threads are std::threads claiming tiles from a counter (which thread renders a tile never
// changes its result, so any thread count gives the same bits).
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>
#include <immintrin.h>
#include <type_traits>

namespace {

constexpr int R_MX = 0, R_MY = 1, R_Q0 = 2, R_Q1 = 3, R_Q2 = 4, R_O = 5, R_CUT = 6, R_INVQ0 = 7, R_X0 = 8,
              R_X1 = 9, R_Y0 = 10, R_Y1 = 11, R_FEAT = 12;
constexpr int NARROW_BOX = 8;

// exp(-s) for s in [0, cut] (cut <= ln(255) + margin < 6): Cody-Waite reduction x = k ln2 + r, |r| <= ln2/2, a
// degree-7 Taylor polynomial (float32; float64 keeps libm's exp) of exp(r) in Horner form and 2^k built in the exponent bits.
// No calls and no branches: the loop over a candidate list vectorises.
inline float exp_neg(float s) {
    float x = -s;
    // round to nearest by the 1.5 * 2^23 shift (|x log2 e| < 2^22): no call, vectorises
    float k = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
    float r = x - k * 0.693145751953125f;
    r = r - k * 1.428606765330187045e-06f;
    float p = 1.0f / 5040.0f;
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    int32_t ki = static_cast<int32_t>(k);
    int32_t bits = (ki + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, 4);
    return p * scale;
}

inline double exp_neg(double s) { return std::exp(-s); }

int g_variant = 3;  // experiments: 0 = the plain port, 1 = vector backward, 2 = fused one-pass forward, 3 = AVX2 candidates (narrow boxes and spans), 4 = AVX2 narrow boxes only

// one entry's recorded pairs, RGB or RGB + depth (NF = 3, 4): every pair of one entry is a different pixel, so the
// loop carries nothing but its sums and runs as vectors (gathers of the pixels' state); the pixels' new B are
// stored in nb and scattered after the loop.
template <class T, int NF>
inline void entry_backward_simd(int64_t j0, int64_t j1, const int32_t* __restrict__ pix, const T* __restrict__ pes,
                                const T* __restrict__ pts, const T* __restrict__ vr, T* __restrict__ B,
                                T* __restrict__ nb, uint32_t* __restrict__ np_, const T* __restrict__ xc,
                                const T* __restrict__ yc, int64_t tw, const T* e_, T alpha_clamp, T half, T* g) {
    const T mx = e_[R_MX], my = e_[R_MY], q0 = e_[R_Q0], q1 = e_[R_Q1], q2 = e_[R_Q2], o = e_[R_O];
    const T c0 = e_[R_FEAT], c1 = e_[R_FEAT + 1], c2 = e_[R_FEAT + 2], c3 = NF == 4 ? e_[R_FEAT + 3] : T(0);
    T g_mx = 0, g_my = 0, g_q0 = 0, g_q1 = 0, g_q2 = 0, g_o = 0, g0 = 0, g1 = 0, g2 = 0, g3 = 0;
    const int64_t n = j1 - j0;
    const uint32_t utw = uint32_t(tw);
#pragma omp simd reduction(+ : g_mx, g_my, g_q0, g_q1, g_q2, g_o, g0, g1, g2, g3)
    for (int64_t i = 0; i < n; ++i) {
        const uint32_t pv = uint32_t(pix[j0 + i]);
        const uint32_t lx = pv & 0xFFFFu, ly = pv >> 16;
        const uint32_t p = ly * utw + lx;
        const T e = pes[j0 + i], Ti = pts[j0 + i];
        const T raw = o * e;
        const T alpha = raw < alpha_clamp ? raw : alpha_clamp;
        const T w = alpha * Ti;
        const T v0 = vr[p * NF], v1 = vr[p * NF + 1], v2 = vr[p * NF + 2];
        g0 += w * v0;
        g1 += w * v1;
        g2 += w * v2;
        T d = v0 * c0 + v1 * c1 + v2 * c2;
        if (NF == 4) {
            const T v3 = vr[p * NF + 3];
            g3 += w * v3;
            d += v3 * c3;
        }
        const T bp = B[p];
        const T diff = d - bp;
        nb[i] = bp + alpha * diff;
        np_[i] = p;
        const T v_alpha = raw <= alpha_clamp ? Ti * diff : T(0);
        g_o += v_alpha * e;
        const T v_sigma = -v_alpha * alpha;
        const T hv = half * v_sigma;
        const T dx = xc[lx] - mx, dy = yc[ly] - my;
        g_q0 += hv * dx * dx;
        g_q1 += v_sigma * dx * dy;
        g_q2 += hv * dy * dy;
        g_mx += -v_sigma * (q0 * dx + q1 * dy);
        g_my += -v_sigma * (q1 * dx + q2 * dy);
    }
    for (int64_t i = 0; i < n; ++i) B[np_[i]] = nb[i];
    g[0] = g_mx, g[1] = g_my, g[2] = g_q0, g[3] = g_q1, g[4] = g_q2, g[5] = g_o, g[6] = g0, g[7] = g1, g[8] = g2;
    g[9] = g3;
}

struct Tile {
    int64_t c, x_lo, x_hi, y_lo, y_hi;
};

// left-packing permutations: for each 8-bit mask, the indices of its set lanes first (AVX2 has no compress)
struct PackLut {
    alignas(32) int32_t idx[256][8];
    PackLut() {
        for (int m = 0; m < 256; ++m) {
            int k = 0;
            for (int i = 0; i < 8; ++i)
                if (m >> i & 1) idx[m][k++] = i;
            for (; k < 8; ++k) idx[m][k] = 0;
        }
    }
};
const PackLut kPack;

// pass 1, float32, one pixel row's columns [rx0, rx1) of a tile (dy from the mean, row = its first pixel's index in
// the tile): 8 pixels per vector, the candidates (sigma within [0, cut], pixel not stopped) left-packed into cs /
// cp / cq at n (8 slots of padding after the tile's pixels). Returns the new count.
inline uint32_t row_candidates_avx2(int64_t rx0, int64_t rx1, int64_t x_lo, float dy, int64_t row, int32_t hq,
                                    float mx, float q0, float q1, float q2, float cut, float half, const uint8_t* dn,
                                    uint32_t* cpp, int32_t* cqp, float* csp, uint32_t n) {
    const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256 vq0 = _mm256_set1_ps(q0), vdy = _mm256_set1_ps(dy);
    const __m256 vh = _mm256_set1_ps(half), vcut = _mm256_set1_ps(cut), vzero = _mm256_setzero_ps();
    const __m256 q2dy2 = _mm256_set1_ps(q2 * dy * dy), q1dy = _mm256_set1_ps(q1 * dy);
    for (int64_t x = rx0; x < rx1; x += 8) {
        const __m256i valid = _mm256_cmpgt_epi32(_mm256_set1_epi32(int32_t(rx1 - x)), iota);
        const __m256i col = _mm256_add_epi32(_mm256_set1_epi32(int32_t(x - x_lo)), iota);
        const __m256 dx = _mm256_sub_ps(_mm256_add_ps(_mm256_set1_ps(float(x) + half), _mm256_cvtepi32_ps(iota)),
                                        _mm256_set1_ps(mx));
        // sigma = half (q0 dx^2 + q2 dy^2) + q1 dx dy
        const __m256 sig = _mm256_fmadd_ps(q1dy, dx, _mm256_mul_ps(vh, _mm256_fmadd_ps(_mm256_mul_ps(vq0, dx), dx, q2dy2)));
        uint64_t d8;
        std::memcpy(&d8, dn + row + (x - x_lo), 8);
        const __m256i d = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(int64_t(d8)));
        __m256i ok = _mm256_andnot_si256(_mm256_cmpgt_epi32(d, _mm256_setzero_si256()), valid);
        const __m256 in = _mm256_and_ps(_mm256_cmp_ps(sig, vzero, _CMP_GE_OQ), _mm256_cmp_ps(sig, vcut, _CMP_LE_OQ));
        ok = _mm256_and_si256(ok, _mm256_castps_si256(in));
        const int m = _mm256_movemask_ps(_mm256_castsi256_ps(ok));
        if (m == 0) continue;
        const __m256i perm = _mm256_load_si256(reinterpret_cast<const __m256i*>(kPack.idx[m]));
        _mm256_storeu_ps(csp + n, _mm256_permutevar8x32_ps(sig, perm));
        const __m256i pidx = _mm256_add_epi32(_mm256_set1_epi32(int32_t(row)), col);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(cpp + n), _mm256_permutevar8x32_epi32(pidx, perm));
        const __m256i q = _mm256_or_si256(_mm256_set1_epi32(hq), col);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(cqp + n), _mm256_permutevar8x32_epi32(q, perm));
        n += uint32_t(__builtin_popcount(m));
    }
    return n;
}

// pass 1 of a narrow box (<= 8 px wide), float32: each row's pixels as one 8-lane vector (the columns' terms
// computed once per box), the candidates left-packed as in row_candidates_avx2. Returns the new count.
inline uint32_t narrow_candidates_avx2(int64_t x0, int64_t x1, int64_t y0, int64_t y1, const Tile& tl, int64_t tw,
                                       float mx, float my, float q0, float q1, float q2, float cut, float half,
                                       const float* yc, const uint8_t* dn, uint32_t* cpp, int32_t* cqp,
                                       float* csp) {
    uint32_t n = 0;
    const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256i valid = _mm256_cmpgt_epi32(_mm256_set1_epi32(int32_t(x1 - x0)), iota);
    const __m256 dx = _mm256_sub_ps(_mm256_add_ps(_mm256_set1_ps(float(x0) + half), _mm256_cvtepi32_ps(iota)),
                                    _mm256_set1_ps(mx));
    const __m256 vh = _mm256_set1_ps(half), vcut = _mm256_set1_ps(cut), vzero = _mm256_setzero_ps();
    const __m256 q0dx2 = _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(q0), dx), dx);
    const __m256 q1dx = _mm256_mul_ps(_mm256_set1_ps(q1), dx);
    const __m256i col = _mm256_add_epi32(_mm256_set1_epi32(int32_t(x0 - tl.x_lo)), iota);
    for (int64_t py = y0; py < y1; ++py) {
        const float dy = yc[py - tl.y_lo] - my;
        const __m256 sig = _mm256_fmadd_ps(q1dx, _mm256_set1_ps(dy),
                                           _mm256_mul_ps(vh, _mm256_add_ps(q0dx2, _mm256_set1_ps(q2 * dy * dy))));
        const int64_t row = (py - tl.y_lo) * tw;
        const int32_t hq = int32_t((py - tl.y_lo) << 16);
        uint64_t d8;
        std::memcpy(&d8, dn + row + (x0 - tl.x_lo), 8);
        const __m256i d = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(int64_t(d8)));
        __m256i ok = _mm256_andnot_si256(_mm256_cmpgt_epi32(d, _mm256_setzero_si256()), valid);
        const __m256 in = _mm256_and_ps(_mm256_cmp_ps(sig, vzero, _CMP_GE_OQ), _mm256_cmp_ps(sig, vcut, _CMP_LE_OQ));
        ok = _mm256_and_si256(ok, _mm256_castps_si256(in));
        const int m = _mm256_movemask_ps(_mm256_castsi256_ps(ok));
        if (m == 0) continue;
        const __m256i perm = _mm256_load_si256(reinterpret_cast<const __m256i*>(kPack.idx[m]));
        _mm256_storeu_ps(csp + n, _mm256_permutevar8x32_ps(sig, perm));
        const __m256i pidx = _mm256_add_epi32(_mm256_set1_epi32(int32_t(row)), col);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(cpp + n), _mm256_permutevar8x32_epi32(pidx, perm));
        const __m256i q = _mm256_or_si256(_mm256_set1_epi32(hq), col);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(cqp + n), _mm256_permutevar8x32_epi32(q, perm));
        n += uint32_t(__builtin_popcount(m));
    }
    return n;
}

inline int64_t interleave(int64_t i, int64_t n) {
    int64_t half = (n + 1) / 2;
    return i < half ? 2 * i : 2 * (i - half) + 1;
}

inline Tile tile_of(int64_t t, int64_t n_tiles, int64_t tile_w, int64_t tile_size, int64_t width, int64_t height) {
    int64_t c = t / n_tiles, tt = t % n_tiles;
    int64_t x_lo = (tt % tile_w) * tile_size, y_lo = (tt / tile_w) * tile_size;
    return {c, x_lo, std::min(x_lo + tile_size, width), y_lo, std::min(y_lo + tile_size, height)};
}

template <class F>
void run_tiles(int64_t n_all, int threads, F fn) {
    std::atomic<int64_t> next{0};
    auto work = [&]() {
        for (;;) {
            int64_t it = next.fetch_add(1, std::memory_order_relaxed);
            if (it >= n_all) break;
            fn(interleave(it, n_all));
        }
    };
    if (threads <= 1) {
        work();
        return;
    }
    std::vector<std::thread> pool;
    for (int i = 1; i < threads; ++i) pool.emplace_back(work);
    work();
    for (auto& th : pool) th.join();
}

template <class T>
void composite_forward(const T* ent, int64_t n_rec, const int64_t* offsets, int64_t n_cam, int64_t width,
                       int64_t height, int64_t tile_size, int64_t tile_w, const T* cst, const T* backgrounds,
                       int use_bg, int64_t n_feat, T* render, T* t_final, const int64_t* pbase, int64_t* pend,
                       int32_t* pix, T* pes, T* pts, int record, int threads) {
    const T alpha_clamp = cst[0], athr = cst[1], tstop = cst[2], half = cst[3], one = cst[4], zero = cst[5],
            two = cst[6];
    const int64_t tile_h = (height + tile_size - 1) / tile_size;
    const int64_t n_tiles = tile_w * tile_h;
    run_tiles(n_cam * n_tiles, threads, [&](int64_t t) {
        Tile tl = tile_of(t, n_tiles, tile_w, tile_size, width, height);
        const int64_t lo = offsets[t], hi = offsets[t + 1];
        const int64_t tw = tl.x_hi - tl.x_lo, th = tl.y_hi - tl.y_lo, n_px = tw * th;
        thread_local std::vector<T> Tv, acc, cs, xc, yc;
        thread_local std::vector<uint8_t> done;
        thread_local std::vector<uint32_t> cp;
        thread_local std::vector<int32_t> cq;
        Tv.assign(n_px, one);
        acc.assign(n_px * n_feat, zero);
        done.assign(n_px + 8, 0);
        cp.resize(n_px + 8);
        cq.resize(n_px + 8);
        cs.resize(n_px + 8);
        xc.resize(tw);
        yc.resize(th);
        for (int64_t i = 0; i < tw; ++i) xc[i] = T(tl.x_lo + i) + half;
        for (int64_t i = 0; i < th; ++i) yc[i] = T(tl.y_lo + i) + half;
        T* __restrict__ Tp = Tv.data();
        T* __restrict__ ap = acc.data();
        uint8_t* __restrict__ dn = done.data();
        uint32_t* __restrict__ cpp = cp.data();
        int32_t* __restrict__ cqp = cq.data();
        T* __restrict__ csp = cs.data();
        int64_t n_done = 0;
        int64_t j = pbase[t];
        for (int64_t k = lo; k < hi; ++k) {
            if (n_done == n_px) {
                for (int64_t kk = k; kk < hi; ++kk) pend[kk] = j;
                break;
            }
            const T* e_ = ent + k * n_rec;
            int64_t x0 = std::max<int64_t>(int64_t(e_[R_X0]), tl.x_lo), x1 = std::min<int64_t>(int64_t(e_[R_X1]), tl.x_hi);
            int64_t y0 = std::max<int64_t>(int64_t(e_[R_Y0]), tl.y_lo), y1 = std::min<int64_t>(int64_t(e_[R_Y1]), tl.y_hi);
            if (x0 < x1 && y0 < y1) {
                const T mx = e_[R_MX], my = e_[R_MY], q0 = e_[R_Q0], q1 = e_[R_Q1], q2 = e_[R_Q2];
                const T o = e_[R_O], cut = e_[R_CUT], inv_q0 = e_[R_INVQ0];
                uint32_t n = 0;
                const bool narrow = x1 - x0 <= NARROW_BOX;
                const T* colf = e_ + R_FEAT;
                const bool fused = g_variant == 2;
                if constexpr (std::is_same_v<T, float>) {
                    if (g_variant >= 3 && g_variant != 4 ? narrow : (g_variant == 4 && narrow)) {
                        n = narrow_candidates_avx2(x0, x1, y0, y1, tl, tw, mx, my, q0, q1, q2, cut, half, yc.data(),
                                                   dn, cpp, cqp, csp);
                        goto candidates_done;
                    }
                }
                for (int64_t py = y0; py < y1; ++py) {
                    const T dy = yc[py - tl.y_lo] - my;
                    int64_t rx0 = x0, rx1 = x1;
                    if (!narrow && q0 > zero) {
                        const T b = q1 * dy;
                        const T disc = b * b - q0 * (q2 * dy * dy - two * cut);
                        if (disc < zero) {
                            rx1 = x0;
                        } else {
                            const T root = std::sqrt(disc);
                            const T l = mx - half + (-b - root) * inv_q0;
                            const T h = mx - half + (-b + root) * inv_q0;
                            rx0 = std::max<int64_t>(x0, int64_t(std::floor(l)));
                            rx1 = std::max<int64_t>(std::min<int64_t>(x1, int64_t(std::floor(h)) + 1), x0);
                        }
                    }
                    const int64_t row = (py - tl.y_lo) * tw - tl.x_lo;
                    const int32_t hq = int32_t((py - tl.y_lo) << 16);
                    if constexpr (std::is_same_v<T, float>) {
                        if (g_variant == 3 || g_variant >= 5) {
                            n = row_candidates_avx2(rx0, rx1, tl.x_lo, dy, row + tl.x_lo, hq, mx, q0, q1, q2, cut,
                                                    half, dn, cpp, cqp, csp, n);
                            continue;
                        }
                    }
                    if (fused) {  // one pass: the test, the inlined exp and the compositing per pixel
                        for (int64_t px = rx0; px < rx1; ++px) {
                            const uint32_t p = uint32_t(row + px);
                            const T dx = xc[px - tl.x_lo] - mx;
                            const T sigma = half * (q0 * dx * dx + q2 * dy * dy) + q1 * dx * dy;
                            if (!((sigma >= zero) & (sigma <= cut)) || dn[p]) continue;
                            const T e = exp_neg(sigma);
                            const T alpha = std::min(alpha_clamp, o * e);
                            if (alpha < athr) continue;
                            const T tp = Tp[p];
                            const T nt = tp * (one - alpha);
                            if (nt <= tstop) {
                                dn[p] = 1;
                                ++n_done;
                                continue;
                            }
                            Tp[p] = nt;
                            const T w = alpha * tp;
                            T* a = ap + size_t(p) * n_feat;
                            for (int64_t f = 0; f < n_feat; ++f) a[f] += w * colf[f];
                            if (record) {
                                pix[j] = hq | int32_t(px - tl.x_lo);
                                pes[j] = e;
                                pts[j] = tp;
                                ++j;
                            }
                        }
                        continue;
                    }
                    for (int64_t px = rx0; px < rx1; ++px) {
                        const uint32_t p = uint32_t(row + px);
                        const T dx = xc[px - tl.x_lo] - mx;
                        const T sigma = half * (q0 * dx * dx + q2 * dy * dy) + q1 * dx * dy;
                        cpp[n] = p;
                        cqp[n] = hq | int32_t(px - tl.x_lo);
                        csp[n] = sigma;
                        n += uint32_t((sigma >= zero) & (sigma <= cut) & (dn[p] == 0));
                    }
                }
            candidates_done:
                if (g_variant == 5) {  // timing split only: pass 1 alone
                    pend[k] = j;
                    continue;
                }
#pragma GCC ivdep
                for (uint32_t i = 0; i < n; ++i) csp[i] = exp_neg(csp[i]);
                if (g_variant == 6) {  // timing split only: passes 1 and 2
                    pend[k] = j;
                    continue;
                }
                const T* col = e_ + R_FEAT;
                if constexpr (std::is_same_v<T, float>) {
                    if (g_variant == 7) {  // pass 3 with 8 candidates a vector: alpha, threshold and stop tests
                        const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
                        const __m256 vo = _mm256_set1_ps(o), vcl = _mm256_set1_ps(alpha_clamp);
                        const __m256 vth = _mm256_set1_ps(athr), vts = _mm256_set1_ps(tstop);
                        const __m256 vone = _mm256_set1_ps(1.0f);
                        alignas(32) float a_[8], t_[8], n_[8];
                        alignas(32) int32_t p_[8];
                        for (uint32_t i = 0; i < n; i += 8) {
                            const __m256 valid = _mm256_castsi256_ps(
                                _mm256_cmpgt_epi32(_mm256_set1_epi32(int32_t(n - i)), iota));
                            const __m256 e = _mm256_loadu_ps(csp + i);
                            const __m256i pv = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(cpp + i));
                            const __m256 alpha = _mm256_min_ps(vcl, _mm256_mul_ps(vo, e));
                            const __m256 keep = _mm256_and_ps(valid, _mm256_cmp_ps(alpha, vth, _CMP_GE_OQ));
                            if (_mm256_movemask_ps(keep) == 0) continue;
                            const __m256 tp = _mm256_mask_i32gather_ps(vone, Tp, pv, keep, 4);
                            const __m256 nt = _mm256_mul_ps(tp, _mm256_sub_ps(vone, alpha));
                            const __m256 stop = _mm256_and_ps(keep, _mm256_cmp_ps(nt, vts, _CMP_LE_OQ));
                            int ms = _mm256_movemask_ps(stop);
                            int mc = _mm256_movemask_ps(_mm256_andnot_ps(stop, keep));
                            _mm256_store_ps(a_, alpha);
                            _mm256_store_ps(t_, tp);
                            _mm256_store_ps(n_, nt);
                            _mm256_store_si256(reinterpret_cast<__m256i*>(p_), pv);
                            while (ms) {
                                const int l = __builtin_ctz(ms);
                                ms &= ms - 1;
                                dn[p_[l]] = 1;
                                ++n_done;
                            }
                            while (mc) {
                                const int l = __builtin_ctz(mc);
                                mc &= mc - 1;
                                const uint32_t p = uint32_t(p_[l]);
                                Tp[p] = n_[l];
                                const float w = a_[l] * t_[l];
                                float* a = ap + size_t(p) * n_feat;
                                a[0] += w * col[0];
                                a[1] += w * col[1];
                                a[2] += w * col[2];
                                if (n_feat == 4) a[3] += w * col[3];
                                else for (int64_t f = 3; f < n_feat; ++f) a[f] += w * col[f];
                                if (record) {
                                    pix[j] = cqp[i + l];
                                    pes[j] = csp[i + l];
                                    pts[j] = t_[l];
                                    ++j;
                                }
                            }
                        }
                        pend[k] = j;
                        continue;
                    }
                }
                for (uint32_t i = 0; i < n; ++i) {
                    const uint32_t p = cpp[i];
                    const T e = csp[i];
                    const T alpha = std::min(alpha_clamp, o * e);
                    if (alpha < athr) continue;
                    const T tp = Tp[p];
                    const T nt = tp * (one - alpha);
                    if (nt <= tstop) {
                        dn[p] = 1;
                        ++n_done;
                        continue;
                    }
                    Tp[p] = nt;
                    const T w = alpha * tp;
                    T* a = ap + size_t(p) * n_feat;
                    if (n_feat == 3) {
                        a[0] += w * col[0];
                        a[1] += w * col[1];
                        a[2] += w * col[2];
                    } else if (n_feat == 4) {
                        a[0] += w * col[0];
                        a[1] += w * col[1];
                        a[2] += w * col[2];
                        a[3] += w * col[3];
                    } else {
                        for (int64_t f = 0; f < n_feat; ++f) a[f] += w * col[f];
                    }
                    if (record) {
                        pix[j] = cqp[i];
                        pes[j] = e;
                        pts[j] = tp;
                        ++j;
                    }
                }
            }
            pend[k] = j;
        }
        for (int64_t py = tl.y_lo; py < tl.y_hi; ++py) {
            for (int64_t px = tl.x_lo; px < tl.x_hi; ++px) {
                const int64_t p = (py - tl.y_lo) * tw + (px - tl.x_lo);
                const int64_t o = (tl.c * height + py) * width + px;
                for (int64_t f = 0; f < n_feat; ++f)
                    render[o * n_feat + f] = ap[p * n_feat + f] + (use_bg ? Tp[p] * backgrounds[tl.c * n_feat + f] : zero);
                t_final[o] = Tp[p];
            }
        }
    });
}

template <class T>
void composite_backward(const T* ent, int64_t n_rec, const int64_t* offsets, int64_t n_cam, int64_t width,
                        int64_t height, int64_t tile_size, int64_t tile_w, const T* cst, const T* backgrounds,
                        int use_bg, int64_t n_feat, const T* v_render, const T* v_alphas, const int64_t* pbase,
                        const int64_t* pend, const int32_t* pix, const T* pes, const T* pts, T* slots, int threads) {
    const T alpha_clamp = cst[0], half = cst[3], zero = cst[5];
    const int64_t tile_h = (height + tile_size - 1) / tile_size;
    const int64_t n_tiles = tile_w * tile_h;
    const int64_t n_slot = 6 + n_feat;
    run_tiles(n_cam * n_tiles, threads, [&](int64_t t) {
        Tile tl = tile_of(t, n_tiles, tile_w, tile_size, width, height);
        const int64_t lo = offsets[t], hi = offsets[t + 1];
        const int64_t tw = tl.x_hi - tl.x_lo, th = tl.y_hi - tl.y_lo, n_px = tw * th;
        thread_local std::vector<T> Bv, vrv, xc, yc, gcol, nbv;
        thread_local std::vector<uint32_t> npv;
        nbv.resize(n_px);
        npv.resize(n_px);
        Bv.resize(n_px);
        vrv.resize(n_px * n_feat);
        xc.resize(tw);
        yc.resize(th);
        gcol.resize(n_feat);
        for (int64_t i = 0; i < tw; ++i) xc[i] = T(tl.x_lo + i) + half;
        for (int64_t i = 0; i < th; ++i) yc[i] = T(tl.y_lo + i) + half;
        T* __restrict__ B = Bv.data();
        T* __restrict__ vr = vrv.data();
        for (int64_t py = tl.y_lo; py < tl.y_hi; ++py) {
            for (int64_t px = tl.x_lo; px < tl.x_hi; ++px) {
                const int64_t p = (py - tl.y_lo) * tw + (px - tl.x_lo);
                const int64_t o = (tl.c * height + py) * width + px;
                T bp = -v_alphas[o];
                for (int64_t f = 0; f < n_feat; ++f) {
                    const T vf = v_render[o * n_feat + f];
                    vr[p * n_feat + f] = vf;
                    if (use_bg) bp += vf * backgrounds[tl.c * n_feat + f];
                }
                B[p] = bp;
            }
        }
        for (int64_t k = hi - 1; k >= lo; --k) {
            T g_mx = zero, g_my = zero, g_q0 = zero, g_q1 = zero, g_q2 = zero, g_o = zero;
            T g0 = zero, g1 = zero, g2 = zero, g3 = zero;
            for (int64_t f = 0; f < n_feat; ++f) gcol[f] = zero;
            const int64_t j0 = k > lo ? pend[k - 1] : pbase[t];
            const int64_t j1 = pend[k];
            const T* e_ = ent + k * n_rec;
            if (g_variant >= 1 && (n_feat == 3 || n_feat == 4) && j1 > j0) {
                T g[10];
                if (n_feat == 3)
                    entry_backward_simd<T, 3>(j0, j1, pix, pes, pts, vr, B, nbv.data(), npv.data(), xc.data(),
                                              yc.data(), tw, e_, alpha_clamp, half, g);
                else
                    entry_backward_simd<T, 4>(j0, j1, pix, pes, pts, vr, B, nbv.data(), npv.data(), xc.data(),
                                              yc.data(), tw, e_, alpha_clamp, half, g);
                g_mx = g[0], g_my = g[1], g_q0 = g[2], g_q1 = g[3], g_q2 = g[4], g_o = g[5];
                g0 = g[6], g1 = g[7], g2 = g[8], g3 = g[9];
            } else if (j1 > j0) {
                const T mx = e_[R_MX], my = e_[R_MY], q0 = e_[R_Q0], q1 = e_[R_Q1], q2 = e_[R_Q2], o = e_[R_O];
                const T* col = e_ + R_FEAT;
                const T c0 = n_feat > 0 ? col[0] : zero, c1 = n_feat > 1 ? col[1] : zero;
                const T c2 = n_feat > 2 ? col[2] : zero, c3 = n_feat > 3 ? col[3] : zero;
                for (int64_t jj = j0; jj < j1; ++jj) {
                    const uint32_t pv = uint32_t(pix[jj]);
                    const uint32_t lx = pv & 0xFFFFu, ly = pv >> 16;
                    const size_t p = size_t(ly) * size_t(tw) + lx;
                    const T e = pes[jj], Ti = pts[jj];
                    const T raw = o * e;
                    const T alpha = std::min(alpha_clamp, raw);
                    const T w = alpha * Ti;
                    T d;
                    if (n_feat == 3 || n_feat == 4) {
                        const T* v = vr + p * n_feat;
                        g0 += w * v[0];
                        g1 += w * v[1];
                        g2 += w * v[2];
                        d = v[0] * c0 + v[1] * c1 + v[2] * c2;
                        if (n_feat == 4) {
                            g3 += w * v[3];
                            d += v[3] * c3;
                        }
                    } else {
                        d = zero;
                        for (int64_t f = 0; f < n_feat; ++f) {
                            const T vc = vr[p * n_feat + f];
                            gcol[f] += w * vc;
                            d += vc * col[f];
                        }
                    }
                    const T bp = B[p];
                    const T diff = d - bp;
                    B[p] = bp + alpha * diff;
                    if (raw <= alpha_clamp) {
                        const T v_alpha = Ti * diff;
                        g_o += v_alpha * e;
                        const T v_sigma = -v_alpha * alpha;
                        const T hv = half * v_sigma;
                        const T dx = xc[lx] - mx, dy = yc[ly] - my;
                        g_q0 += hv * dx * dx;
                        g_q1 += v_sigma * dx * dy;
                        g_q2 += hv * dy * dy;
                        g_mx -= v_sigma * (q0 * dx + q1 * dy);
                        g_my -= v_sigma * (q1 * dx + q2 * dy);
                    }
                }
            }
            T* s = slots + k * n_slot;
            s[0] = g_mx;
            s[1] = g_my;
            s[2] = g_q0;
            s[3] = g_q1;
            s[4] = g_q2;
            s[5] = g_o;
            if (n_feat == 3 || n_feat == 4) {
                gcol[0] = g0;
                gcol[1] = g1;
                gcol[2] = g2;
                if (n_feat == 4) gcol[3] = g3;
            }
            for (int64_t f = 0; f < n_feat; ++f) s[6 + f] = gcol[f];
        }
    });
}

}  // namespace

extern "C" {

#define NC_FORWARD(NAME, T)                                                                                           \
    void NAME(const T* ent, int64_t n_rec, const int64_t* offsets, int64_t n_cam, int64_t width, int64_t height,     \
              int64_t tile_size, int64_t tile_w, const T* cst, const T* bg, int use_bg, int64_t n_feat, T* render,    \
              T* t_final, const int64_t* pbase, int64_t* pend, int32_t* pix, T* pes, T* pts, int record,             \
              int threads) {                                                                                          \
        composite_forward<T>(ent, n_rec, offsets, n_cam, width, height, tile_size, tile_w, cst, bg, use_bg, n_feat,  \
                             render, t_final, pbase, pend, pix, pes, pts, record, threads);                          \
    }
#define NC_BACKWARD(NAME, T)                                                                                          \
    void NAME(const T* ent, int64_t n_rec, const int64_t* offsets, int64_t n_cam, int64_t width, int64_t height,     \
              int64_t tile_size, int64_t tile_w, const T* cst, const T* bg, int use_bg, int64_t n_feat,              \
              const T* v_render, const T* v_alphas, const int64_t* pbase, const int64_t* pend, const int32_t* pix,   \
              const T* pes, const T* pts, T* slots, int threads) {                                                    \
        composite_backward<T>(ent, n_rec, offsets, n_cam, width, height, tile_size, tile_w, cst, bg, use_bg, n_feat, \
                              v_render, v_alphas, pbase, pend, pix, pes, pts, slots, threads);                       \
    }

NC_FORWARD(nc_composite_forward_f32, float)
NC_FORWARD(nc_composite_forward_f64, double)
NC_BACKWARD(nc_composite_backward_f32, float)
NC_BACKWARD(nc_composite_backward_f64, double)

int nc_abi_version() { return 1; }
void nc_set_variant(int v) { g_variant = v; }
}

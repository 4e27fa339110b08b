/* flowhold's compiled kernels: the reader's record scan with its CRC check, and the CSV writer's
 * number formatting (issue 17).
 *
 * Each function is a compiled copy of a numpy formulation in the Python package, which stays the
 * definition and the fallback when no C compiler is available:
 *   fh_scan       <- companion/recordings/tlog_reader.py, _find_packets pass 1 (_claimed_end, _parse_headers,
 *                    _check_crc), candidate by candidate;
 *   fh_tables, fh_fields <- companion/recordings/tlog_reader.py, _tables_numpy (_decode_fast), the first
 *                    the tables' rows, the second the fields asked for;
 *   fh_csv_rows   <- companion/tools/csv_format.py, format_rows (itself Python's % formatting);
 *   fh_searchsorted_* <- numpy.searchsorted on a sorted array (companion/native.py, searchsorted);
 *   fh_lfilter2   <- scipy.signal.lfilter of order 2 (companion/diagnose/filters.py, lfilter), and
 *                    fh_lfilter2_segments the same over many stretches (filters.lfilter_segments);
 *   fh_wind_scan  <- companion/diagnose/closed_loop/wind.py, _scan_gains and its argmax.
 * The tests hold each equal to the one it copies (tests/test_native.py). Loaded through ctypes by
 * companion/native.py, which compiles this file once with the system's C compiler.
 *
 * Plain C99, no library beyond libc and libm; no global state besides the CRC tables, which are
 * filled once by fh_init (called by the loader before anything else).
 */

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <limits.h>
#include <string.h>

#define STX_V1 0xFE
#define STX_V2 0xFD
#define TIME_HEADER_LEN 8
#define SIGNATURE_LEN 13
#define HEADER_LEN_V1 6
#define HEADER_LEN_V2 10
#define CRC_LEN 2

/* ABI version: companion/native.py refuses a library whose fh_version differs */
int32_t fh_version(void) { return 14; }

/* ------------------------------------------------------------------------------------------- */
/* CRC-16/MCRF4XX (X.25). crc_tab[k][b]: the CRC contribution of byte b followed by k zero bytes
 * (slicing by 16). The CRC is affine over GF(2): crc(init, bytes) = crc(init, zeros of the same
 * length) ^ crc(0, bytes), and leading zero bytes leave crc(0, .) unchanged; crc_init[L] is
 * crc(0xFFFF, L zero bytes). So a packet's CRC is computed in whole 16-byte blocks ending with its
 * last byte, the bytes before its first zeroed (the numpy formulation's trick, tlog_reader._check_crc). */

#define CRC_MAX 320
static uint16_t crc_tab[16][256];
static uint16_t crc_init[CRC_MAX + 1];

void fh_init(void) {
    for (int b = 0; b < 256; b++) {
        uint8_t tmp = (uint8_t)(b ^ (b << 4));
        crc_tab[0][b] = (uint16_t)((tmp << 8) ^ (tmp << 3) ^ (tmp >> 4));
    }
    for (int k = 1; k < 16; k++)
        for (int b = 0; b < 256; b++) {
            uint16_t prev = crc_tab[k - 1][b];
            crc_tab[k][b] = (uint16_t)((prev >> 8) ^ crc_tab[0][prev & 0xFF]);
        }
    uint16_t c = 0xFFFF;
    for (int k = 0; k <= CRC_MAX; k++) {
        crc_init[k] = c;
        c = (uint16_t)((c >> 8) ^ crc_tab[0][c & 0xFF]);
    }
}

static inline uint16_t crc_step(uint16_t crc, uint8_t b) { return (uint16_t)((crc >> 8) ^ crc_tab[0][(crc ^ b) & 0xFF]); }

static inline uint16_t crc_bytes(uint16_t crc, const uint8_t *p, int64_t n) {
    while (n-- > 0) crc = crc_step(crc, *p++);
    return crc;
}

static inline uint16_t slice8(uint64_t w, int k) { /* the 8 bytes of w followed by k zero bytes */
    return (uint16_t)(crc_tab[k + 7][w & 0xFF] ^ crc_tab[k + 6][(w >> 8) & 0xFF] ^ crc_tab[k + 5][(w >> 16) & 0xFF] ^
                      crc_tab[k + 4][(w >> 24) & 0xFF] ^ crc_tab[k + 3][(w >> 32) & 0xFF] ^
                      crc_tab[k + 2][(w >> 40) & 0xFF] ^ crc_tab[k + 1][(w >> 48) & 0xFF] ^ crc_tab[k][w >> 56]);
}

/* The MAVLink CRC of the len bytes at p followed by the byte extra (little-endian machine; up to
 * 15 bytes before p are read, and must be readable, when p - base >= 15). */
static inline uint16_t crc_packet(const uint8_t *base, const uint8_t *p, int64_t len, uint8_t extra) {
    int64_t total = len + 1;
    int64_t blocks = (total + 15) / 16;
    int64_t pad = 16 * blocks - total;
    if (total > CRC_MAX || p - pad < base) return crc_step(crc_bytes(0xFFFF, p, len), extra);
    const uint8_t *q = p - pad;
    uint16_t crc = 0;
    for (int64_t b = 0; b < blocks; b++, q += 16) {
        uint64_t w0, w1;
        memcpy(&w0, q, 8);
        memcpy(&w1, q + 8, 8);
        if (b == 0) { /* the bytes before p are zeros */
            if (pad >= 8) {
                w0 = 0;
                w1 &= ~0ULL << (8 * (pad - 8));
            } else {
                w0 &= ~0ULL << (8 * pad);
            }
        }
        if (b == blocks - 1) w1 = (w1 & 0x00FFFFFFFFFFFFFFULL) | (uint64_t)extra << 56; /* extra after the data */
        w0 ^= crc;
        crc = (uint16_t)(slice8(w0, 8) ^ slice8(w1, 0));
    }
    return (uint16_t)(crc ^ crc_init[total]);
}

/* CRC-16/MCRF4XX of n bytes (no crc_extra), and the MAVLink CRC of n bytes then extra: for the tests. */
uint16_t fh_crc16(const uint8_t *p, int64_t n) { return crc_bytes(0xFFFF, p, n); }
uint16_t fh_crc_packet(const uint8_t *base, const uint8_t *p, int64_t n, uint8_t extra) {
    return crc_packet(base, p, n, extra);
}

/* ------------------------------------------------------------------------------------------- */
/* The reader's first pass */

static inline int is_stx(uint8_t b) { return (uint8_t)(b - STX_V2) < 2; }

/* Which of the SCAN_BYTES bytes at p are 0xFD or 0xFE: bit SCAN_BIT * j for byte j. */
#if defined(__SSE2__) && !defined(FH_NO_SSE2)
#include <emmintrin.h>
#define SCAN_BYTES 16
#define SCAN_BIT 1
static inline uint64_t stx_bits(const uint8_t *p) {
    __m128i v = _mm_loadu_si128((const __m128i *)p);
    __m128i hit = _mm_or_si128(_mm_cmpeq_epi8(v, _mm_set1_epi8((char)STX_V2)),
                               _mm_cmpeq_epi8(v, _mm_set1_epi8((char)STX_V1)));
    return (uint64_t)(uint32_t)_mm_movemask_epi8(hit);
}
#else
#define SCAN_BYTES 8
#define SCAN_BIT 8
static inline uint64_t stx_bits(const uint8_t *p) {
    uint64_t w;
    memcpy(&w, p, 8);
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_BIG_ENDIAN__
    w = __builtin_bswap64(w); /* byte j in bits 8j..8j+7 */
#endif
    /* bit 7 of each byte that is 0xFD or 0xFE: 0xFD-0xFF (the low 7 bits plus 3 carry into bit
     * 7, no carry crosses a byte), less 0xFF (a zero byte of ~w, the exact test) */
    uint64_t ge = ((w & 0x7F7F7F7F7F7F7F7FULL) + 0x0303030303030303ULL) & w & 0x8080808080808080ULL;
    uint64_t nw = ~w;
    uint64_t ff = ~(((nw & 0x7F7F7F7F7F7F7F7FULL) + 0x7F7F7F7F7F7F7F7FULL) | nw) & 0x8080808080808080ULL;
    return (ge & ~ff) >> 7; /* bit 8j */
}
#endif

/* where a packet starting at s ends, by its STX, length and signed flag (_claimed_end) */
static inline int64_t claimed_end(const uint8_t *buf, int64_t s) {
    int v2 = buf[s] == STX_V2;
    int64_t length = buf[s + 1];
    int64_t sig = v2 ? (buf[s + 2] & 1) * SIGNATURE_LEN : 0;
    return s + (v2 ? HEADER_LEN_V2 + CRC_LEN : HEADER_LEN_V1 + CRC_LEN) + length + sig;
}

static inline int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }

/* Whether the record chain goes on for two more records after a packet ending at end (which fits:
 * end <= n_bytes): the file ends there, or the next record's STX follows the time header, and
 * after that record either the file ends or another STX follows (fh_scan's "chained"). */
static inline int chained_after(const uint8_t *buf, int64_t n_bytes, int64_t end) {
    if (end == n_bytes) return 1;
    int64_t nxt = min64(end + TIME_HEADER_LEN, n_bytes);
    if (!is_stx(buf[nxt])) return 0;
    int64_t end2 = claimed_end(buf, nxt);
    return end2 == n_bytes || is_stx(buf[min64(end2 + TIME_HEADER_LEN, n_bytes)]);
}

/* The message id in the header at h (MAVLink 2: 24 bits; MAVLink 1: one byte). */
static inline int64_t msgid_of(const uint8_t *h) {
    return h[0] == STX_V2 ? ((int64_t)h[7] | (int64_t)h[8] << 8 | (int64_t)h[9] << 16) : h[5];
}

/* Pass 1 of _find_packets over the candidate packet starts (bytes 0xFD, 0xFE) in [pos, stop):
 * a candidate from which the record chain goes on for two more records and whose packet fits in
 * the file ("chained") is a good packet if its header is decodable (a message id with
 * known[id], incompatibility flags at most "signed") and its CRC (with extra[id]) holds; its
 * header fields are written to the good_* arrays. A candidate that fits but is not chained goes
 * to other[]. ``buf`` holds n_bytes of file and at least 512 bytes of zeros after them.
 * Stops early when either output is full; returns the position to resume from (stop when
 * done) and the counts in *n_good, *n_other. */
int64_t fh_scan(const uint8_t *buf, int64_t n_bytes, int64_t pos, int64_t stop, const uint8_t *known,
                const uint8_t *extra, int64_t tab_len, int64_t cap_good, int64_t *good_s, uint8_t *good_hdr,
                int16_t *good_plen, int16_t *good_total, int32_t *good_msgid, uint8_t *good_sysid,
                uint8_t *good_compid, uint64_t *good_t, int64_t *n_good, int64_t cap_other, int64_t *other,
                int64_t *n_other) {
    int64_t ng = 0, no = 0;
    if (pos < TIME_HEADER_LEN) pos = TIME_HEADER_LEN;
    if (stop > n_bytes) stop = n_bytes;
    for (int64_t block = pos & ~(int64_t)(SCAN_BYTES - 1); block < stop; block += SCAN_BYTES) {
        uint64_t m = stx_bits(buf + block); /* buf is padded past n_bytes */
        if (block < pos) m &= ~0ULL << (SCAN_BIT * (pos - block));
        if (stop - block < SCAN_BYTES) m &= (1ULL << (SCAN_BIT * (stop - block))) - 1;
        while (m) {
            int64_t s = block + __builtin_ctzll(m) / SCAN_BIT;
            m &= m - 1;
            if (ng >= cap_good || no >= cap_other) {
                *n_good = ng;
                *n_other = no;
                return s;
            }
            int64_t end = claimed_end(buf, s);
            if (end > n_bytes) continue; /* does not fit */
            if (!chained_after(buf, n_bytes, end)) {
                other[no++] = s;
                continue;
            }
            const uint8_t *h = buf + s;
            int v2 = h[0] == STX_V2;
            int64_t plen = h[1];
            uint8_t flags = v2 ? h[2] : 0;
            int64_t hdr = v2 ? HEADER_LEN_V2 : HEADER_LEN_V1;
            int64_t msgid = msgid_of(h);
            int64_t id = msgid < tab_len - 1 ? msgid : tab_len - 1;
            if (!known[id] || (flags & 0xFE)) continue;
            int64_t covered = hdr - 1 + plen;
            uint16_t stored = (uint16_t)(h[1 + covered] | h[2 + covered] << 8);
            if (crc_packet(buf, h + 1, covered, extra[id]) != stored) continue;
            uint64_t t_be;
            memcpy(&t_be, h - TIME_HEADER_LEN, 8);
            good_s[ng] = s;
            good_hdr[ng] = (uint8_t)hdr;
            good_plen[ng] = (int16_t)plen;
            good_total[ng] = (int16_t)(hdr + plen + CRC_LEN + ((flags & 1) ? SIGNATURE_LEN : 0));
            good_msgid[ng] = (int32_t)msgid;
            good_sysid[ng] = v2 ? h[5] : h[3];
            good_compid[ng] = v2 ? h[6] : h[4];
            good_t[ng] = __builtin_bswap64(t_be); /* big-endian on the wire */
            ng++;
        }
    }
    *n_good = ng;
    *n_other = no;
    return stop;
}

/* How many good packets fh_scan will find in [pos, stop), by following the record chain instead
 * of judging every candidate: from the first chained candidate (fh_scan's test) each record's
 * successor is taken to start right after it, and a record is counted when its header is
 * decodable (known[id], flags at most "signed"). No CRC is computed. On a file whose records are
 * whole and whose CRCs hold, this is fh_scan's count exactly; elsewhere it is only a size hint
 * (the caller checks the scan's count against it). Lets each thread of a parallel scan write
 * straight into its rows of one set of arrays. */
int64_t fh_count(const uint8_t *buf, int64_t n_bytes, int64_t pos, int64_t stop, const uint8_t *known,
                 int64_t tab_len) {
    int64_t count = 0;
    if (pos < TIME_HEADER_LEN) pos = TIME_HEADER_LEN;
    if (stop > n_bytes) stop = n_bytes;
    while (pos < stop) {
        int64_t s = pos;
        if (!is_stx(buf[s])) {
            pos++;
            continue;
        }
        int64_t end = claimed_end(buf, s);
        if (end > n_bytes || !chained_after(buf, n_bytes, end)) {
            pos++;
            continue;
        }
        const uint8_t *h = buf + s;
        uint8_t flags = h[0] == STX_V2 ? h[2] : 0;
        int64_t msgid = msgid_of(h);
        int64_t id = msgid < tab_len - 1 ? msgid : tab_len - 1;
        if (known[id] && !(flags & 0xFE)) count++;
        pos = end + TIME_HEADER_LEN;
    }
    return count;
}

/* The fields of n payloads of one message type, decoded straight into their columns: row i's
 * payload is buf[at[i]:at[i] + min(plen[i], size)] followed by zeros up to size bytes (MAVLink 2
 * truncates trailing zeros; a longer payload is cut, as pymavlink does); field f is the
 * width[f] bytes at offset[f] of it, copied to out[f] + i * width[f] (little-endian wire
 * order: the caller checks the machine is little-endian). Equals _decode_fast's structured
 * view of the same rows. */
static inline void copy_bytes(uint8_t *o, const uint8_t *a, int64_t w) {
    switch (w) { /* the common widths as plain loads and stores */
    case 1: *o = *a; break;
    case 2: memcpy(o, a, 2); break;
    case 4: memcpy(o, a, 4); break;
    case 8: memcpy(o, a, 8); break;
    default: memcpy(o, a, (size_t)w);
    }
}

/* The reader's tables in one pass over the packets i0 <= i < i1 in file order (_tables with
 * _decode_fast): packet i of group g = group[i] (-1: not here) becomes the next row r = rows[g]++
 * of that group's table (rows[g] on entry: the group's packets before i0, so that ranges of
 * packets can be done apart, in any order or at once): t_out[g][r] = t_s[i], sysid/compid,
 * record_out[g][r] = i, and each field f of the group (fields first_field[g] ..
 * first_field[g + 1] - 1) is the width[f] bytes at offset[f] of the payload (buf[s[i] + hdr[i]:],
 * plen[i] bytes, zero-padded to size[g]; longer: cut), copied to out[f] + r * width[f]
 * (little-endian wire order: the caller checks the machine is little-endian). Returns 0, or -1
 * if a size is over 255. */
int32_t fh_tables(const uint8_t *buf, int64_t i0, int64_t i1, const int64_t *s, const uint8_t *hdr,
                  const int16_t *plen, const int32_t *group, const double *t_s, const uint8_t *sysid,
                  const uint8_t *compid, int32_t ngroups, const int64_t *size, const int64_t *first_field,
                  const int64_t *offset, const int64_t *width, uint8_t *const *out, double *const *t_out,
                  uint8_t *const *sysid_out, uint8_t *const *compid_out, int64_t *const *record_out, int64_t *rows) {
    uint8_t padded[256];
    for (int32_t g = 0; g < ngroups; g++)
        if (size[g] > 255) return -1;
    for (int64_t i = i0; i < i1; i++) {
        int32_t g = group[i];
        if (g < 0) continue;
        int64_t r = rows[g]++;
        t_out[g][r] = t_s[i];
        sysid_out[g][r] = sysid[i];
        compid_out[g][r] = compid[i];
        record_out[g][r] = i;
        const uint8_t *payload = buf + s[i] + hdr[i];
        int64_t sz = size[g];
        if (plen[i] < sz) {
            int64_t k = plen[i] > 0 ? plen[i] : 0;
            memcpy(padded, payload, (size_t)k);
            memset(padded + k, 0, (size_t)(sz - k));
            payload = padded;
        }
        for (int64_t f = first_field[g]; f < first_field[g + 1]; f++)
            copy_bytes(out[f] + r * width[f], payload + offset[f], width[f]);
    }
    return 0;
}

/* Some fields of one message type's rows, decoded straight into their columns (the reader's
 * columns made on first use: _tables_native's lazy fields): row r is packet i = record[r], whose
 * payload is buf[s[i] + hdr[i]:], plen[i] bytes, zero-padded to size (longer: cut); field f (of
 * nf) is the width[f] bytes at offset[f] of it, copied to out[f] + r * width[f] (little-endian
 * wire order). The same bytes fh_tables copies for those fields. Returns 0, or -1 if a field
 * lies outside the size or the size is over 255. */
int32_t fh_fields(const uint8_t *buf, int64_t n, const int64_t *record, const int64_t *s, const uint8_t *hdr,
                  const int16_t *plen, int64_t size, int32_t nf, const int64_t *offset, const int64_t *width,
                  uint8_t *const *out) {
    if (size > 255) return -1;
    for (int32_t f = 0; f < nf; f++)
        if (offset[f] < 0 || width[f] < 0 || offset[f] + width[f] > size) return -1;
    uint8_t padded[256];
    for (int64_t r = 0; r < n; r++) {
        int64_t i = record[r];
        const uint8_t *payload = buf + s[i] + hdr[i];
        if (plen[i] < size) {
            int64_t k = plen[i] > 0 ? plen[i] : 0;
            memcpy(padded, payload, (size_t)k);
            memset(padded + k, 0, (size_t)(size - k));
            payload = padded;
        }
        for (int32_t f = 0; f < nf; f++) copy_bytes(out[f] + r * width[f], payload + offset[f], width[f]);
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------- */
/* Sorted search */

/* np.searchsorted(a, v, side) for a sorted a (n values) and any queries v (m values): out[j] is
 * the number of a's values before v[j] (left: a[i] < v[j]; right: not v[j] < a[i]), with numpy's
 * order for floats (NaN after every number). Queries in non-decreasing order, the common case
 * (record numbers, times), are found by galloping on from the previous answer: O(m log gap)
 * rather than O(m log n); a query below the previous one starts again from the whole array. */
#define LT_F64(x, y) ((x) < (y) || ((y) != (y) && (x) == (x)))
#define LT_I64(x, y) ((x) < (y))
#define SEARCHSORTED(NAME, T, LT)                                                                                  \
    void NAME(const T *a, int64_t n, const T *v, int64_t m, int32_t right, int64_t *out) {                     \
        int64_t lo = 0;                                                                                          \
        for (int64_t j = 0; j < m; j++) {                                                                        \
            T key = v[j];                                                                                        \
            if (j == 0 || LT(key, v[j - 1])) lo = 0; /* else: the answer is at or after the previous */       \
            /* before(i): a[i] comes before key (left: a[i] < key; right: !(key < a[i])) */                     \
            int64_t hi, step = 1;                                                                                \
            if (lo < n && (right ? !LT(key, a[lo]) : LT(a[lo], key))) {                                          \
                int64_t last = lo; /* gallop: a[last] is before key */                                           \
                hi = lo + 1;                                                                                     \
                while (hi < n && (right ? !LT(key, a[hi]) : LT(a[hi], key))) {                                   \
                    last = hi;                                                                                   \
                    step *= 2;                                                                                   \
                    hi = last + step;                                                                            \
                }                                                                                                \
                if (hi > n) hi = n;                                                                              \
                lo = last + 1; /* the answer is in [lo, hi] */                                                   \
                while (lo < hi) {                                                                                \
                    int64_t mid = lo + (hi - lo) / 2;                                                            \
                    if (right ? !LT(key, a[mid]) : LT(a[mid], key)) lo = mid + 1;                                \
                    else hi = mid;                                                                               \
                }                                                                                                \
            }                                                                                                    \
            out[j] = lo;                                                                                         \
        }                                                                                                        \
    }
SEARCHSORTED(fh_searchsorted_f64, double, LT_F64)
SEARCHSORTED(fh_searchsorted_i64, int64_t, LT_I64)

/* ------------------------------------------------------------------------------------------- */
/* CSV rows */

enum { COL_FLOAT = 0, COL_INT = 1, COL_TEXT = 2 };

/* 10^k for k = -32..40, the nearest doubles (exact for 0..22) */
static const double POW10[73] = {
    1e-32, 1e-31, 1e-30, 1e-29, 1e-28, 1e-27, 1e-26, 1e-25, 1e-24, 1e-23, 1e-22, 1e-21, 1e-20, 1e-19, 1e-18,
    1e-17, 1e-16, 1e-15, 1e-14, 1e-13, 1e-12, 1e-11, 1e-10, 1e-9,  1e-8,  1e-7,  1e-6,  1e-5,  1e-4,  1e-3,
    1e-2,  1e-1,  1e0,   1e1,   1e2,   1e3,   1e4,   1e5,   1e6,   1e7,   1e8,   1e9,   1e10,  1e11,  1e12,
    1e13,  1e14,  1e15,  1e16,  1e17,  1e18,  1e19,  1e20,  1e21,  1e22,  1e23,  1e24,  1e25,  1e26,  1e27,
    1e28,  1e29,  1e30,  1e31,  1e32,  1e33,  1e34,  1e35,  1e36,  1e37,  1e38,  1e39,  1e40};
#define POW10_AT(k) POW10[(k) + 32]

static const char DIGITS2[201] = "00010203040506070809101112131415161718192021222324252627282930313233343536373839"
                                 "40414243444546474849505152535455565758596061626364656667686970717273747576777879"
                                 "8081828384858687888990919293949596979899";

static inline void put8(char *o, uint32_t v) { /* v < 10^8 as exactly 8 digits */
    uint32_t a = v / 10000, b = v % 10000;
    memcpy(o, DIGITS2 + 2 * (a / 100), 2);
    memcpy(o + 2, DIGITS2 + 2 * (a % 100), 2);
    memcpy(o + 4, DIGITS2 + 2 * (b / 100), 2);
    memcpy(o + 6, DIGITS2 + 2 * (b % 100), 2);
}

/* the 8 ASCII digits of v < 10^8 (leading zeros included) as a little-endian word: the most
 * significant digit in the lowest byte */
static inline uint64_t digits8(uint32_t v) {
    uint32_t a = v / 10000, b = v % 10000;
    uint16_t d0, d1, d2, d3;
    memcpy(&d0, DIGITS2 + 2 * (a / 100), 2);
    memcpy(&d1, DIGITS2 + 2 * (a % 100), 2);
    memcpy(&d2, DIGITS2 + 2 * (b / 100), 2);
    memcpy(&d3, DIGITS2 + 2 * (b % 100), 2);
    return (uint64_t)d0 | (uint64_t)d1 << 16 | (uint64_t)d2 << 32 | (uint64_t)d3 << 48;
}

/* Bytes j.. of the 16-byte string (s0, s1) stored at o: 16 bytes are written (the caller's slot
 * has room; what follows the digits is overwritten or past the text's length). */
static inline void put_from(char *o, uint64_t s0, uint64_t s1, int j) {
    uint64_t t0, t1;
    if (j == 0) {
        t0 = s0;
        t1 = s1;
    } else if (j < 8) {
        t0 = (s0 >> (8 * j)) | (s1 << (64 - 8 * j));
        t1 = s1 >> (8 * j);
    } else if (j == 8) {
        t0 = s1;
        t1 = 0;
    } else {
        t0 = s1 >> (8 * (j - 8));
        t1 = 0;
    }
    memcpy(o, &t0, 8);
    memcpy(o + 8, &t1, 8);
}

/* floor(log10(ax)) for a positive normal double, up to the exactness of the POW10 thresholds
 * (a value within an ulp of a power of ten may get the power's exponent: both choices print
 * the same text, see format_g_fast); INT32_MIN when outside the table (the slow path). */
static inline int64_t decimal_exponent(double ax) {
    uint64_t bits;
    memcpy(&bits, &ax, 8);
    int64_t e2 = (int64_t)((bits >> 52) & 0x7FF) - 1023;
    int64_t e = (e2 * 78913) >> 18; /* floor(e2 * log10(2)) for |e2| < 1700 */
    if (e < -32 || e + 1 > 40) return INT32_MIN;
    if (ax >= POW10_AT(e + 1)) e++;
    return e;
}

/* "%.<P>g" of a finite non-zero x whose P significant digits are certain from one scaling by an
 * exact power of ten (the rule of csv_format._floats: m = |x| * 10^(P-1-e) is within m * 2^-53
 * of the exact product, so rint(m) is the correctly rounded digits unless m is that close to a
 * half; an exponent one too small or too large gives digits outside [10^(P-1), 10^P)); returns
 * the length written, or 0 when x must go the slow way. */
static inline int format_g_fast(double x, int P, char *o) {
    double ax = fabs(x);
    if (!(ax >= 1e-300 && ax < 1e300)) return 0;
    int64_t e = decimal_exponent(ax);
    if (e == INT32_MIN) return 0;
    int64_t k = P - 1 - e;
    if (k > 22 || k < -22) return 0;
    double m = k >= 0 ? ax * POW10_AT(k) : ax / POW10_AT(-k);
    double d = rint(m);
    double frac = m - floor(m);
    double lo = POW10_AT(P - 1), hi = POW10_AT(P);
    if (!(fabs(frac - 0.5) > hi * 1e-15) || d < lo || d >= hi) return 0;
    uint64_t D = (uint64_t)d;
    int nd = P; /* the digits shown: D's trailing zeros dropped (at most P - 1: D >= 10^(P-1)),
                 * counted 8, 4, 2, 1 at a time: no loop as long as the zeros */
    if (D % 10 == 0) {
        uint64_t q = D;
        if (q % 100000000u == 0) q /= 100000000u, nd -= 8;
        if (q % 10000u == 0) q /= 10000u, nd -= 4;
        if (q % 100u == 0) q /= 100u, nd -= 2;
        if (q % 10u == 0) nd -= 1;
    }
    /* the P digits as a string S of two little-endian words (S[0] in the lowest byte of s0), kept
     * in registers and only stored: text written and read back at once stalls on its stores */
    uint64_t s0, s1;
    if (P <= 8) {
        s0 = digits8((uint32_t)D) >> (8 * (8 - P));
        s1 = 0;
    } else {
        uint64_t hi = digits8((uint32_t)(D / 100000000u)), lo = digits8((uint32_t)(D % 100000000u));
        int k = P - 8; /* 1..7 digits in hi */
        s0 = (hi >> (8 * (8 - k))) | (lo << (8 * k));
        s1 = lo >> (8 * (8 - k));
    }
    char *p = o;
    if (x < 0) *p++ = '-';
    if (e < -4 || e >= P) { /* d.ddde+XX */
        *p++ = (char)(s0 & 0xFF);
        if (nd > 1) {
            *p++ = '.';
            put_from(p, s0, s1, 1);
            p += nd - 1;
        }
        *p++ = 'e';
        int64_t ae = e < 0 ? -e : e;
        *p++ = e < 0 ? '-' : '+';
        if (ae >= 100) *p++ = (char)('0' + ae / 100 % 10);
        *p++ = (char)('0' + ae / 10 % 10);
        *p++ = (char)('0' + ae % 10);
    } else if (e < 0) { /* 0.000ddd */
        *p++ = '0';
        *p++ = '.';
        for (int64_t j = 0; j < -e - 1; j++) *p++ = '0';
        put_from(p, s0, s1, 0);
        p += nd;
    } else { /* ddd.ddd, or the digits up to the point (zeros included) */
        int whole = (int)e + 1;
        put_from(p, s0, s1, 0);
        p += whole;
        if (nd > whole) {
            *p++ = '.';
            put_from(p, s0, s1, whole);
            p += nd - whole;
        }
    }
    return (int)(p - o);
}

/* "%.<P>g" of any double as Python's % operator spells it */
static inline int format_g(double x, int P, char *o) {
    if (isnan(x)) {
        memcpy(o, "nan", 3);
        return 3;
    }
    if (isinf(x)) {
        if (x < 0) {
            memcpy(o, "-inf", 4);
            return 4;
        }
        memcpy(o, "inf", 3);
        return 3;
    }
    if (x == 0) {
        if (signbit(x)) {
            memcpy(o, "-0", 2);
            return 2;
        }
        o[0] = '0';
        return 1;
    }
    int len = format_g_fast(x, P, o);
    if (len) return len;
    /* the C library's %g: correctly rounded like Python's (tests/test_native.py holds them equal) */
    char tmp[64];
    len = snprintf(tmp, sizeof tmp, "%.*g", P, x);
    memcpy(o, tmp, (size_t)len);
    return len;
}

static inline int format_d(int64_t v, char *o) {
    uint64_t a = v < 0 ? (uint64_t)0 - (uint64_t)v : (uint64_t)v;
    char *p = o;
    if (v < 0) *p++ = '-';
    if (a < 100000000u) {
        char tmp[8];
        put8(tmp, (uint32_t)a);
        int skip = 0;
        while (skip < 7 && tmp[skip] == '0') skip++;
        memcpy(p, tmp + skip, (size_t)(8 - skip));
        return (int)(p + 8 - skip - o);
    }
    char tmp[24];
    int n = 0;
    do {
        tmp[n++] = (char)('0' + a % 10);
        a /= 10;
    } while (a);
    while (n) *p++ = tmp[--n];
    return (int)(p - o);
}

#define CSV_BLOCK 64 /* rows formatted column by column before they are laid out */
#define CSV_SLOT 32  /* bytes per formatted number (at most 23 are text; format_g_fast's 16-byte
                      * stores of digits reach at most byte 32) */

/* Rows [0, n) of ncols columns as CSV text into out (capacity cap bytes; the caller sizes it
 * with a row bound: the widest text of each column plus a separator), returning the bytes
 * written (-1 if cap was too small, or the scratch memory could not be had).
 * kind[c]: COL_FLOAT (data[c]: float64, digits[c] significant digits), COL_INT (int64) or
 * COL_TEXT (int32 codes into the texts [text_off[c][j], text_off[c][j + 1]) of text_blob[c]).
 * The numbers of a block of rows are formatted one column at a time (each column read in
 * order, its values alike in shape), then the rows laid out from the slots. */
int64_t fh_csv_rows(int64_t n, int32_t ncols, const int32_t *kind, const void *const *data, const int32_t *digits,
                    const uint8_t *const *text_blob, const int64_t *const *text_off, uint8_t *out, int64_t cap,
                    int64_t row_bound) {
    char *slots = malloc((size_t)ncols * CSV_BLOCK * CSV_SLOT);
    uint8_t *lens = malloc((size_t)ncols * CSV_BLOCK);
    if (slots == NULL || lens == NULL) {
        free(slots);
        free(lens);
        return -1;
    }
    uint8_t *p = out;
    for (int64_t a = 0; a < n; a += CSV_BLOCK) {
        int64_t m = n - a < CSV_BLOCK ? n - a : CSV_BLOCK;
        if ((p - out) + m * row_bound + CSV_SLOT > cap) {
            free(slots);
            free(lens);
            return -1;
        }
        for (int32_t c = 0; c < ncols; c++) {
            char *slot = slots + (int64_t)c * CSV_BLOCK * CSV_SLOT;
            uint8_t *len = lens + (int64_t)c * CSV_BLOCK;
            if (kind[c] == COL_FLOAT) {
                const double *x = (const double *)data[c] + a;
                int P = digits[c];
                for (int64_t i = 0; i < m; i++) len[i] = (uint8_t)format_g(x[i], P, slot + i * CSV_SLOT);
            } else if (kind[c] == COL_INT) {
                const int64_t *v = (const int64_t *)data[c] + a;
                for (int64_t i = 0; i < m; i++) len[i] = (uint8_t)format_d(v[i], slot + i * CSV_SLOT);
            }
        }
        for (int64_t i = 0; i < m; i++) {
            for (int32_t c = 0; c < ncols; c++) {
                if (kind[c] == COL_TEXT) {
                    int32_t j = ((const int32_t *)data[c])[a + i];
                    int64_t t0 = text_off[c][j], t1 = text_off[c][j + 1];
                    memcpy(p, text_blob[c] + t0, (size_t)(t1 - t0));
                    p += t1 - t0;
                } else { /* a whole slot is copied (out has room), the text's length kept */
                    memcpy(p, slots + ((int64_t)c * CSV_BLOCK + i) * CSV_SLOT, CSV_SLOT);
                    p += lens[(int64_t)c * CSV_BLOCK + i];
                }
                *p++ = c + 1 < ncols ? ',' : '\n';
            }
        }
    }
    free(slots);
    free(lens);
    return p - out;
}

/* ------------------------------------------------------------------------------------------- */
/* scipy.signal.lfilter of a second-order filter (b, a normalised by a[0]), direct form II
 * transposed as scipy's RAWFILTER computes it, term for term: y = z0 + b0 x,
 * z0 = z1 + x b1 - y a1, z1 = x b2 - y a2. z: the initial state, left as the final one. */
void fh_lfilter2(const double *b, const double *a, const double *x, int64_t n, double *z, double *y) {
    double z0 = z[0], z1 = z[1];
    const double b0 = b[0], b1 = b[1], b2 = b[2], a1 = a[1], a2 = a[2];
    for (int64_t k = 0; k < n; k++) {
        double xk = x[k];
        double yk = z0 + b0 * xk;
        z0 = z1 + xk * b1 - yk * a1;
        z1 = xk * b2 - yk * a2;
        y[k] = yk;
    }
    z[0] = z0;
    z[1] = z1;
}

/* ------------------------------------------------------------------------------------------- */
/* The wind search's scan (companion/diagnose/closed_loop/wind.py, _scan_gains and its argmax),
 * for R residuals at once: for each r, the largest explained sum of squares of one mean shift over
 * pooled windows j1..j2-1 and its flat index j1 m + j2 - 1 in _scan_gains's (m, m) array, the
 * first maximum in row-major order as numpy.argmax gives it (-1 at index 0 when no window is
 * allowed). ce (R, 2, m + 1): each residual's cumulative sums from 0; cw (m + 1) the cumulative
 * weights; b0, b1 (m) the pooled windows' start and end times. A window is allowed when it lasts
 * at least min_s and has weight; its gain is (dx^2 + dy^2) / weight, as numpy computes it. */
void fh_wind_scan(const double *ce, int64_t R, int64_t m, const double *cw, const double *b0, const double *b1,
                  double min_s, double *gain, int64_t *flat) {
    for (int64_t r = 0; r < R; r++) {
        const double *cx = ce + r * 2 * (m + 1), *cy = cx + (m + 1);
        double best = -1.0;
        int64_t at = 0;
        for (int64_t j1 = 0; j1 < m; j1++) {
            const double x1 = cx[j1], y1 = cy[j1], w1 = cw[j1], t1 = b0[j1];
            for (int64_t j2 = j1 + 1; j2 <= m; j2++) {
                double nwt = cw[j2] - w1;
                if (!(b1[j2 - 1] - t1 >= min_s) || !(nwt > 0)) continue;
                double dx = cx[j2] - x1, dy = cy[j2] - y1;
                double v = (dx * dx + dy * dy) / nwt;
                if (v > best) {
                    best = v;
                    at = j1 * m + j2 - 1;
                }
            }
        }
        gain[r] = best;
        flat[r] = at;
    }
}

/* ------------------------------------------------------------------------------------------- */
/* fh_lfilter2 over each of nseg stretches [starts[s], stops[s]) of x, each started from its own
 * state zi[2 s], zi[2 s + 1] (companion/diagnose/filters.py, lfilter_segments: lfilter once per
 * stretch); y outside the stretches is left as it is. */
void fh_lfilter2_segments(const double *b, const double *a, const double *x, const int64_t *starts,
                          const int64_t *stops, int64_t nseg, const double *zi, double *y) {
    for (int64_t s = 0; s < nseg; s++) {
        double z[2] = {zi[2 * s], zi[2 * s + 1]};
        if (stops[s] > starts[s]) fh_lfilter2(b, a, x + starts[s], stops[s] - starts[s], z, y + starts[s]);
    }
}

/* ------------------------------------------------------------------------------------------- */
/* y(t - delay) at every frame, each of the `rows` rows of y and dy (rows, n): its value and rate
 * (companion/diagnose/closed_loop/flowmodel.py: FlowProblem._shift_plan and _shifted with idx
 * None), term for term: cubic Hermite between frames j, j + 1, the query time held at its frame's
 * segment's ends (seg_t0: the segment's first time, seg_last: its last frame). */
void fh_hermite_shift(const double *t, int64_t n, const double *seg_t0, const int64_t *seg_last, const double *y,
                      const double *dy, int64_t rows, double delay, double *out) {
    int64_t j = 0;
    for (int64_t k = 0; k < n; k++) {
        double tq = t[k] - delay, hi = t[seg_last[k]];
        if (tq < seg_t0[k]) tq = seg_t0[k];
        if (tq > hi) tq = hi;
        /* searchsorted(t, tq, "right") - 1: the last frame at or before tq (tq moves on with k) */
        while (j > 0 && t[j] > tq) j--;
        while (j + 1 < n && t[j + 1] <= tq) j++;
        int64_t jj = (t[j] <= tq) ? j : j - 1;
        if (jj > n - 2) jj = n - 2;
        if (jj < 0) jj = 0;
        int64_t lim = seg_last[k] - 1 > 0 ? seg_last[k] - 1 : 0;
        if (jj > lim) jj = lim;
        double hh = t[jj + 1] - t[jj];
        double u = (tq - t[jj]) / hh;
        if (u < 0.0) u = 0.0;
        if (u > 1.0) u = 1.0;
        double om = 1.0 - u, sq = om * om;
        double w00 = (1.0 + 2.0 * u) * sq, w10 = (u * sq) * hh, w01 = (u * u) * (3.0 - 2.0 * u);
        double w11 = ((u * u) * (u - 1.0)) * hh;
        for (int64_t i = 0; i < rows; i++) {
            const double *yi = y + i * n, *di = dy + i * n;
            out[i * n + k] = w00 * yi[jj] + w10 * di[jj] + w01 * yi[jj + 1] + w11 * di[jj + 1];
        }
    }
}

/* ------------------------------------------------------------------------------------------- */
/* The force channel's pieces of the odometry of each of the `rows` scene-angle rows S (rows, n)
 * (companion/diagnose/closed_loop/flowmodel.py, FlowProblem._odometry_changes), term for term,
 * without its whole-flight arrays: the increments S[k+1] - S[k] (0 where a segment starts at
 * k + 1: first) times the range between frames amid (n - 1) and times 1, summed into X, X's
 * trapezoidal integral IX (dt: n - 1), and per force window [k0, k1] the change of the boundary
 * means (Z[k + h] - Z[k - h]) / den. out (2 [dv from X, dx from IX], 2 [times A, times 1], rows, nw);
 * scratch: 2 n doubles. */
void fh_odometry_changes(const double *S, int64_t rows, int64_t n, const uint8_t *first, const double *amid,
                         const double *dt, const int64_t *k0, const int64_t *k1, const double *den0,
                         const double *den1, int64_t nw, int64_t h, double *scratch, double *out) {
    double *X = scratch, *IX = scratch + n;
    for (int64_t i = 0; i < rows; i++) {
        const double *si = S + i * n;
        for (int m = 0; m < 2; m++) {
            X[0] = 0.0;
            IX[0] = 0.0;
            for (int64_t k = 0; k + 1 < n; k++) {
                double d = first[k + 1] ? 0.0 : si[k + 1] - si[k];
                X[k + 1] = X[k] + (m == 0 ? amid[k] * d : d);
                IX[k + 1] = IX[k] + (0.5 * (X[k + 1] + X[k])) * dt[k];
            }
            double *dv = out + ((0 * 2 + m) * rows + i) * nw, *dx = out + ((1 * 2 + m) * rows + i) * nw;
            for (int64_t w = 0; w < nw; w++) {
                int64_t a = k0[w], b = k1[w];
                dv[w] = (X[b + h] - X[b - h]) / den1[w] - (X[a + h] - X[a - h]) / den0[w];
                dx[w] = (IX[b + h] - IX[b - h]) / den1[w] - (IX[a + h] - IX[a - h]) / den0[w];
            }
        }
    }
}

/* ------------------------------------------------------------------------------------------- */
/* Each attitude segment's start rate fitted out of the residual
 * (companion/diagnose/closed_loop/attitude.py, AttitudeProblem._free_rate after the free response
 * h (L) is made), term for term, sums in numpy.bincount's order: over the first min(length, L)
 * frames f = start + k of each segment [starts[s], stops[s]), with m = e finite on both rows
 * and fit_mask[f] (fit_mask NULL: every frame), hm = m ? h[k] : 0, den = sum hm hm,
 * num_i = sum (m ? e[i, f] : 0) hm, fitted when den > min_share sum h[k] h[k], and
 * out[i, f] = e[i, f] - coef_i h[k], coef_i = num_i / den (0 when not fitted). out (2, n) holds
 * a copy of e on entry. */
void fh_free_rate(const double *e, int64_t n, const double *h, int64_t L, const int64_t *starts, const int64_t *stops,
                  int64_t nseg, const uint8_t *fit_mask, double min_share, double *out) {
    const double *e0 = e, *e1 = e + n;
    for (int64_t s = 0; s < nseg; s++) {
        int64_t a = starts[s], len = stops[s] - starts[s];
        if (len > L) len = L;
        double den = 0.0, tot = 0.0, num0 = 0.0, num1 = 0.0;
        for (int64_t k = 0; k < len; k++) {
            int64_t f = a + k;
            int m = isfinite(e0[f]) && isfinite(e1[f]) && (fit_mask == NULL || fit_mask[f]);
            double hm = m ? h[k] : 0.0;
            den += hm * hm;
            tot += h[k] * h[k];
            num0 += (m ? e0[f] : 0.0) * hm;
            num1 += (m ? e1[f] : 0.0) * hm;
        }
        int fit = den > min_share * tot;
        double c0 = fit ? num0 / den : 0.0, c1 = fit ? num1 / den : 0.0;
        for (int64_t k = 0; k < len; k++) {
            int64_t f = a + k;
            out[f] = out[f] - c0 * h[k];
            out[n + f] = out[n + f] - c1 * h[k];
        }
    }
}

/* ------------------------------------------------------------------------------------------- */
/* scipy.signal.filtfilt of a second-order filter over each stretch [starts[s], stops[s]) of x
 * (each longer than pad), as companion/diagnose/filters.py's filtfilt_segments computes it, term
 * for term: the stretch's odd extension by pad samples at each end (2 x[first] - x[first + i],
 * 2 x[last] - x[last - i]), fh_lfilter2 from zi times its first sample, reversed, again from zi
 * times the first sample of the reversed output, reversed back into out. out outside the
 * stretches is left as it is. scratch: 3 (longest stretch + 2 pad) doubles. */
void fh_filtfilt2_segments(const double *b, const double *a, const double *zi, const double *x, const int64_t *starts,
                           const int64_t *stops, int64_t nseg, int64_t pad, double *scratch, double *out) {
    for (int64_t s = 0; s < nseg; s++) {
        int64_t s0 = starts[s], s1 = stops[s], len = s1 - s0, m = len + 2 * pad;
        if (len <= pad) continue;
        double *ext = scratch, *y = scratch + m, *y2 = scratch + 2 * m;
        for (int64_t p = 0; p < m; p++) {
            if (p < pad) {
                ext[p] = 2 * x[s0] - x[s0 + pad - p];
            } else if (p >= pad + len) {
                ext[p] = 2 * x[s1 - 1] - x[s1 - 2 - (p - pad - len)];
            } else {
                ext[p] = x[s0 + p - pad];
            }
        }
        double z[2] = {zi[0] * ext[0], zi[1] * ext[0]};
        fh_lfilter2(b, a, ext, m, z, y);
        for (int64_t p = 0; p < m; p++) ext[p] = y[m - 1 - p];
        z[0] = zi[0] * ext[0];
        z[1] = zi[1] * ext[0];
        fh_lfilter2(b, a, ext, m, z, y2);
        for (int64_t i = 0; i < len; i++) out[s0 + i] = y2[m - 1 - (pad + i)];
    }
}

/* ------------------------------------------------------------------------------------------- */
/* The force channel's form-drag regressor (companion/diagnose/closed_loop/flowmodel.py,
 * _FormDrag._form_drag_regressor), term for term, for both rows of the odometry X (2, n): the
 * odometry's rate v over +-h frames within each segment [starts[s], stops[s]) longer than 2 h + 1
 * (clipped at its ends; 0 in shorter segments), q = v |v|, integrated twice (trapezoids through
 * the gaps, dt: n - 1), and per force window [k0, k1] the change of the boundary means
 * (Z[k + h] - Z[k - h]) / den. out (2, nw); scratch: 2 n doubles. */
void fh_form_drag(const double *X, int64_t n, const double *t, const double *dt, const int64_t *starts,
                  const int64_t *stops, int64_t nseg, const int64_t *k0, const int64_t *k1, const double *den0,
                  const double *den1, int64_t nw, int64_t h, double *scratch, double *out) {
    double *v = scratch, *IQ = scratch + n;
    for (int i = 0; i < 2; i++) {
        const double *x = X + i * n;
        for (int64_t k = 0; k < n; k++) v[k] = 0.0;
        for (int64_t s = 0; s < nseg; s++) {
            int64_t a = starts[s], b = stops[s];
            if (!(b - a > 2 * h + 1)) continue;
            for (int64_t k = a; k < b; k++) {
                int64_t lo = k - h, hi = k + h;
                if (lo < a) lo = a;
                if (hi > b - 1) hi = b - 1;
                v[k] = (x[hi] - x[lo]) / (t[hi] - t[lo]);
            }
        }
        /* q = v |v|, Q its integral (running), IQ the integral of Q */
        double Q = 0.0, qprev = v[0] * fabs(v[0]);
        IQ[0] = 0.0;
        for (int64_t k = 0; k + 1 < n; k++) {
            double q = v[k + 1] * fabs(v[k + 1]);
            double Qn = Q + (0.5 * (q + qprev)) * dt[k];
            IQ[k + 1] = IQ[k] + (0.5 * (Qn + Q)) * dt[k];
            Q = Qn;
            qprev = q;
        }
        for (int64_t w = 0; w < nw; w++) {
            int64_t a = k0[w], b = k1[w];
            out[i * nw + w] = (IQ[b + h] - IQ[b - h]) / den1[w] - (IQ[a + h] - IQ[a - h]) / den0[w];
        }
    }
}

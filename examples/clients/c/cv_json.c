/* cv_json.c - see cv_json.h. Written from RFC 8259 and SPEC.md §3.2. */
#include "cv_json.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------------------ validating */

typedef struct {
    const char *p;   /* next byte */
    const char *end; /* one past the last byte */
    char *err;
    size_t errcap;
} cursor;

static int fail(cursor *c, const char *why)
{
    if (c->errcap > 0) {
        snprintf(c->err, c->errcap, "%s", why);
    }
    return -1;
}

static void skip_ws(cursor *c)
{
    while (c->p < c->end && (*c->p == ' ' || *c->p == '\t' || *c->p == '\n' || *c->p == '\r')) {
        c->p++;
    }
}

static int hex_value(char ch)
{
    if (ch >= '0' && ch <= '9') {
        return ch - '0';
    }
    if (ch >= 'a' && ch <= 'f') {
        return ch - 'a' + 10;
    }
    if (ch >= 'A' && ch <= 'F') {
        return ch - 'A' + 10;
    }
    return -1;
}

/* Reads the 4 hex digits after "\u" at p; -1 when they are not 4 hex digits. */
static long read_hex4(const char *p, const char *end)
{
    long value = 0;
    int i;
    if (end - p < 4) {
        return -1;
    }
    for (i = 0; i < 4; i++) {
        int h = hex_value(p[i]);
        if (h < 0) {
            return -1;
        }
        value = value * 16 + h;
    }
    return value;
}

/* Length of the well-formed UTF-8 sequence starting at p (1..4), or 0 when it is not one:
 * overlong forms, UTF-16 surrogates and code points above U+10FFFF are refused. */
static size_t utf8_sequence(const unsigned char *p, const unsigned char *end)
{
    unsigned char b0 = p[0];
    size_t need, i;
    unsigned long cp;
    if (b0 < 0x80) {
        return 1;
    }
    if (b0 >= 0xC2 && b0 <= 0xDF) {
        need = 2;
        cp = b0 & 0x1Fu;
    } else if (b0 >= 0xE0 && b0 <= 0xEF) {
        need = 3;
        cp = b0 & 0x0Fu;
    } else if (b0 >= 0xF0 && b0 <= 0xF4) {
        need = 4;
        cp = b0 & 0x07u;
    } else {
        return 0;
    }
    if ((size_t)(end - p) < need) {
        return 0;
    }
    for (i = 1; i < need; i++) {
        if ((p[i] & 0xC0u) != 0x80u) {
            return 0;
        }
        cp = (cp << 6) | (p[i] & 0x3Fu);
    }
    if ((need == 3 && cp < 0x800) || (need == 4 && cp < 0x10000) || cp > 0x10FFFF ||
        (cp >= 0xD800 && cp <= 0xDFFF)) {
        return 0;
    }
    return need;
}

static int check_string(cursor *c)
{
    c->p++; /* the opening quote */
    while (c->p < c->end) {
        unsigned char ch = (unsigned char)*c->p;
        if (ch == '"') {
            c->p++;
            return 0;
        }
        if (ch < 0x20) {
            return fail(c, "a control character inside a string");
        }
        if (ch == '\\') {
            char e;
            if (c->end - c->p < 2) {
                break;
            }
            e = c->p[1];
            if (e == 'u') {
                long unit = read_hex4(c->p + 2, c->end);
                if (unit < 0) {
                    return fail(c, "a bad \\u escape");
                }
                c->p += 6;
                if (unit >= 0xDC00 && unit <= 0xDFFF) {
                    return fail(c, "a lone UTF-16 low surrogate escape");
                }
                if (unit >= 0xD800 && unit <= 0xDBFF) {
                    long low;
                    if (c->end - c->p < 6 || c->p[0] != '\\' || c->p[1] != 'u') {
                        return fail(c, "a lone UTF-16 high surrogate escape");
                    }
                    low = read_hex4(c->p + 2, c->end);
                    if (low < 0xDC00 || low > 0xDFFF) {
                        return fail(c, "a lone UTF-16 high surrogate escape");
                    }
                    c->p += 6;
                }
                continue;
            }
            if (strchr("\"\\/bfnrt", e) == NULL || e == '\0') {
                return fail(c, "an unknown escape in a string");
            }
            c->p += 2;
            continue;
        }
        {
            size_t n = utf8_sequence((const unsigned char *)c->p, (const unsigned char *)c->end);
            if (n == 0) {
                return fail(c, "invalid UTF-8 in a string");
            }
            c->p += n;
        }
    }
    return fail(c, "an unterminated string");
}

static int is_digit(char ch)
{
    return ch >= '0' && ch <= '9';
}

static int check_number(cursor *c)
{
    const char *start = c->p;
    char copy[512];
    double value;
    size_t n;
    if (c->p < c->end && *c->p == '-') {
        c->p++;
    }
    if (c->p >= c->end || !is_digit(*c->p)) {
        return fail(c, "a bad number");
    }
    if (*c->p == '0') {
        c->p++;
    } else {
        while (c->p < c->end && is_digit(*c->p)) {
            c->p++;
        }
    }
    if (c->p < c->end && *c->p == '.') {
        c->p++;
        if (c->p >= c->end || !is_digit(*c->p)) {
            return fail(c, "a bad fraction");
        }
        while (c->p < c->end && is_digit(*c->p)) {
            c->p++;
        }
    }
    if (c->p < c->end && (*c->p == 'e' || *c->p == 'E')) {
        c->p++;
        if (c->p < c->end && (*c->p == '+' || *c->p == '-')) {
            c->p++;
        }
        if (c->p >= c->end || !is_digit(*c->p)) {
            return fail(c, "a bad exponent");
        }
        while (c->p < c->end && is_digit(*c->p)) {
            c->p++;
        }
    }
    /* SPEC §3.2: numbers outside the double range (1e400) are refused. The program never
     * calls setlocale(), so strtod reads '.' as the decimal point. */
    n = (size_t)(c->p - start);
    if (n >= sizeof copy) {
        return fail(c, "a number too long to check");
    }
    memcpy(copy, start, n);
    copy[n] = '\0';
    errno = 0;
    value = strtod(copy, NULL);
    if (isinf(value) || (errno == ERANGE && (value > 1.0 || value < -1.0))) {
        return fail(c, "a number outside the double range");
    }
    return 0;
}

static int check_literal(cursor *c, const char *word)
{
    size_t n = strlen(word);
    if ((size_t)(c->end - c->p) < n || memcmp(c->p, word, n) != 0) {
        return fail(c, "an unknown literal");
    }
    c->p += n;
    return 0;
}

static int check_value(cursor *c, int depth, cvj_value *out);

static int check_container(cursor *c, int depth, char close)
{
    int first = 1;
    if (depth > CVJ_MAX_DEPTH) {
        return fail(c, "nesting deeper than the client accepts");
    }
    c->p++; /* '{' or '[' */
    for (;;) {
        cvj_value ignored;
        skip_ws(c);
        if (c->p >= c->end) {
            return fail(c, "an unterminated object or array");
        }
        if (*c->p == close && first) {
            c->p++;
            return 0;
        }
        if (!first) {
            if (*c->p == close) {
                c->p++;
                return 0;
            }
            if (*c->p != ',') {
                return fail(c, "a missing comma");
            }
            c->p++;
            skip_ws(c);
        }
        first = 0;
        if (close == '}') {
            if (c->p >= c->end || *c->p != '"') {
                return fail(c, "an object key that is not a string");
            }
            if (check_string(c) != 0) {
                return -1;
            }
            skip_ws(c);
            if (c->p >= c->end || *c->p != ':') {
                return fail(c, "a missing colon");
            }
            c->p++;
        }
        if (check_value(c, depth, &ignored) != 0) {
            return -1;
        }
    }
}

static int check_value(cursor *c, int depth, cvj_value *out)
{
    const char *start;
    int rc;
    skip_ws(c);
    if (c->p >= c->end) {
        return fail(c, "a missing value");
    }
    start = c->p;
    switch (*c->p) {
    case '{':
        out->kind = CVJ_OBJECT;
        rc = check_container(c, depth + 1, '}');
        break;
    case '[':
        out->kind = CVJ_ARRAY;
        rc = check_container(c, depth + 1, ']');
        break;
    case '"':
        out->kind = CVJ_STRING;
        rc = check_string(c);
        break;
    case 't':
        out->kind = CVJ_TRUE;
        rc = check_literal(c, "true");
        break;
    case 'f':
        out->kind = CVJ_FALSE;
        rc = check_literal(c, "false");
        break;
    case 'n':
        out->kind = CVJ_NULL;
        rc = check_literal(c, "null");
        break;
    default:
        out->kind = CVJ_NUMBER;
        rc = check_number(c); /* NaN, Infinity and friends fail here */
        break;
    }
    out->p = start;
    out->n = (size_t)(c->p - start);
    skip_ws(c);
    return rc;
}

int cvj_parse(const char *text, size_t len, cvj_value *root, char *err, size_t errcap)
{
    cursor c;
    c.p = text;
    c.end = text + len;
    c.err = err;
    c.errcap = errcap;
    if (len >= 3 && (unsigned char)text[0] == 0xEF && (unsigned char)text[1] == 0xBB &&
        (unsigned char)text[2] == 0xBF) {
        return fail(&c, "a byte order mark");
    }
    if (check_value(&c, 0, root) != 0) {
        return -1;
    }
    if (c.p != c.end) {
        return fail(&c, "text after the JSON value");
    }
    return 0;
}

/* ------------------------------------------------------------------------------ looking in */

/* The values below were validated by cvj_parse, so stepping over them cannot fail. */
static void step_value(cursor *c, cvj_value *out)
{
    check_value(c, 0, out);
}

static void step_ws(cursor *c)
{
    skip_ws(c);
}

int cvj_member(cvj_value obj, const char *key, cvj_value *out)
{
    cursor c;
    size_t key_len = strlen(key);
    out->kind = CVJ_NONE;
    out->p = NULL;
    out->n = 0;
    if (obj.kind != CVJ_OBJECT) {
        return 0;
    }
    c.p = obj.p + 1;
    c.end = obj.p + obj.n - 1; /* before the closing brace */
    c.err = NULL;
    c.errcap = 0;
    for (;;) {
        cvj_value name, value;
        char decoded[128];
        size_t decoded_len = 0;
        int same;
        step_ws(&c);
        if (c.p >= c.end) {
            break;
        }
        if (*c.p == ',') {
            c.p++;
            step_ws(&c);
        }
        step_value(&c, &name);
        /* A key too long for the buffer cannot be one this client asks for. */
        same = cvj_string(name, decoded, sizeof decoded, &decoded_len) == 0 &&
               decoded_len == key_len && memcmp(decoded, key, key_len) == 0;
        c.p++; /* ':' (step_value left the cursor on it) */
        step_value(&c, &value);
        if (same) {
            *out = value; /* the last occurrence wins, as in most JSON readers */
        }
    }
    if (out->kind == CVJ_NULL) {
        out->kind = CVJ_NONE; /* SPEC §3.2: null is treated as absent */
    }
    return out->kind != CVJ_NONE;
}

int cvj_element(cvj_value arr, size_t index, cvj_value *out)
{
    cursor c;
    size_t i = 0;
    out->kind = CVJ_NONE;
    if (arr.kind != CVJ_ARRAY) {
        return 0;
    }
    c.p = arr.p + 1;
    c.end = arr.p + arr.n - 1;
    c.err = NULL;
    c.errcap = 0;
    for (;;) {
        cvj_value value;
        step_ws(&c);
        if (c.p >= c.end) {
            return 0;
        }
        if (*c.p == ',') {
            c.p++;
        }
        step_value(&c, &value);
        if (i == index) {
            *out = value;
            return 1;
        }
        i++;
    }
}

size_t cvj_length(cvj_value arr)
{
    size_t n = 0;
    cvj_value ignored;
    while (cvj_element(arr, n, &ignored)) {
        n++;
    }
    return n;
}

/* Appends code point cp as UTF-8; -1 when it does not fit. */
static int put_utf8(char *buf, size_t cap, size_t *len, unsigned long cp)
{
    unsigned char tmp[4];
    size_t n, i;
    if (cp < 0x80) {
        tmp[0] = (unsigned char)cp;
        n = 1;
    } else if (cp < 0x800) {
        tmp[0] = (unsigned char)(0xC0 | (cp >> 6));
        tmp[1] = (unsigned char)(0x80 | (cp & 0x3F));
        n = 2;
    } else if (cp < 0x10000) {
        tmp[0] = (unsigned char)(0xE0 | (cp >> 12));
        tmp[1] = (unsigned char)(0x80 | ((cp >> 6) & 0x3F));
        tmp[2] = (unsigned char)(0x80 | (cp & 0x3F));
        n = 3;
    } else {
        tmp[0] = (unsigned char)(0xF0 | (cp >> 18));
        tmp[1] = (unsigned char)(0x80 | ((cp >> 12) & 0x3F));
        tmp[2] = (unsigned char)(0x80 | ((cp >> 6) & 0x3F));
        tmp[3] = (unsigned char)(0x80 | (cp & 0x3F));
        n = 4;
    }
    if (*len + n + 1 > cap) {
        return -1;
    }
    for (i = 0; i < n; i++) {
        buf[(*len)++] = (char)tmp[i];
    }
    return 0;
}

int cvj_string(cvj_value v, char *buf, size_t cap, size_t *outlen)
{
    const char *p, *end;
    size_t len = 0;
    if (v.kind != CVJ_STRING || cap == 0) {
        return -1;
    }
    p = v.p + 1;
    end = v.p + v.n - 1; /* the closing quote */
    while (p < end) {
        unsigned long cp;
        if (*p != '\\') {
            if (len + 2 > cap) {
                return -1;
            }
            buf[len++] = *p++;
            continue;
        }
        switch (p[1]) {
        case 'b': cp = '\b'; break;
        case 'f': cp = '\f'; break;
        case 'n': cp = '\n'; break;
        case 'r': cp = '\r'; break;
        case 't': cp = '\t'; break;
        case 'u': cp = 0; break;
        default: cp = (unsigned char)p[1]; break; /* \" \\ \/ */
        }
        if (p[1] != 'u') {
            p += 2;
        } else {
            cp = (unsigned long)read_hex4(p + 2, end);
            p += 6;
            if (cp >= 0xD800 && cp <= 0xDBFF) { /* validated: a low surrogate follows */
                unsigned long low = (unsigned long)read_hex4(p + 2, end);
                cp = 0x10000 + ((cp - 0xD800) << 10) + (low - 0xDC00);
                p += 6;
            }
        }
        if (put_utf8(buf, cap, &len, cp) != 0) {
            return -1;
        }
    }
    buf[len] = '\0';
    if (outlen != NULL) {
        *outlen = len;
    }
    return 0;
}

int cvj_integer(cvj_value v, long long lo, long long hi, long long *out)
{
    size_t i = 0;
    int negative = 0;
    long long value = 0;
    if (v.kind != CVJ_NUMBER || v.n == 0) {
        return -1;
    }
    if (v.p[0] == '-') {
        negative = 1;
        i = 1;
    }
    if (i == v.n) {
        return -1;
    }
    for (; i < v.n; i++) {
        int digit;
        if (!is_digit(v.p[i])) {
            return -1; /* a fraction or an exponent: not an integer (SPEC §3.2) */
        }
        if (i >= 18 + (size_t)negative) {
            return -1; /* 19 digits or more: beyond any range this client asks for */
        }
        digit = v.p[i] - '0';
        value = value * 10 + digit;
    }
    if (negative) {
        value = -value;
    }
    if (value < lo || value > hi) {
        return -1;
    }
    *out = value;
    return 0;
}

int cvj_boolean(cvj_value v, int *out)
{
    if (v.kind == CVJ_TRUE || v.kind == CVJ_FALSE) {
        *out = v.kind == CVJ_TRUE;
        return 0;
    }
    return -1;
}

/* ------------------------------------------------------------------------------ writing */

void cvj_init(cvj_writer *w, char *buf, size_t cap)
{
    w->buf = buf;
    w->cap = cap;
    w->len = 0;
    w->overflow = 0;
    if (cap > 0) {
        buf[0] = '\0';
    }
}

static void put_bytes(cvj_writer *w, const char *s, size_t n)
{
    if (w->len + n + 1 > w->cap) {
        w->overflow = 1;
        return;
    }
    memcpy(w->buf + w->len, s, n);
    w->len += n;
    w->buf[w->len] = '\0';
}

void cvj_raw(cvj_writer *w, const char *text)
{
    put_bytes(w, text, strlen(text));
}

void cvj_str(cvj_writer *w, const char *s)
{
    put_bytes(w, "\"", 1);
    for (; *s != '\0'; s++) {
        unsigned char ch = (unsigned char)*s;
        if (ch == '"' || ch == '\\') {
            char esc[2];
            esc[0] = '\\';
            esc[1] = (char)ch;
            put_bytes(w, esc, 2);
        } else if (ch < 0x20) {
            char esc[8];
            snprintf(esc, sizeof esc, "\\u%04x", ch);
            put_bytes(w, esc, 6);
        } else {
            put_bytes(w, s, 1); /* UTF-8 passes through; the caller gives valid UTF-8 */
        }
    }
    put_bytes(w, "\"", 1);
}

void cvj_int(cvj_writer *w, long long value)
{
    char text[32];
    int n = snprintf(text, sizeof text, "%lld", value);
    put_bytes(w, text, (size_t)n);
}

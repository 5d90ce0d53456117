/* cv_json.h - just enough JSON (RFC 8259) for the cellvision metadata this client reads and
 * writes (SPEC.md §3.2).
 *
 * Reading: cvj_parse() validates a whole document once (UTF-8, escapes, numbers within the
 * double range, nesting depth); the other functions then look into the validated text without
 * copying it. Unknown members are simply never asked for, members may come in any order, and a
 * member whose value is null counts as absent (§3.2).
 *
 * Writing: a bounded buffer that escapes every string it is given.
 */
#ifndef CV_JSON_H
#define CV_JSON_H

#include <stddef.h>

/* Deeper nesting than this is refused (SPEC §3.2: at least 32 levels must be accepted). */
#define CVJ_MAX_DEPTH 64

typedef enum {
    CVJ_NONE = 0, /* no value: a member that is absent */
    CVJ_NULL,
    CVJ_FALSE,
    CVJ_TRUE,
    CVJ_NUMBER,
    CVJ_STRING,
    CVJ_ARRAY,
    CVJ_OBJECT
} cvj_kind;

/* A value inside a validated document: its text (p, n bytes) and its kind. */
typedef struct {
    const char *p;
    size_t n;
    cvj_kind kind;
} cvj_value;

/* Validates text[0..len) as one JSON value (surrounding whitespace allowed, nothing else).
 * Returns 0 and sets *root, or -1 and writes a reason into err (errcap bytes). */
int cvj_parse(const char *text, size_t len, cvj_value *root, char *err, size_t errcap);

/* The value of member `key` of object `obj` (the last one if the key repeats). Returns 1 when
 * present and not null, else 0 (then out->kind is CVJ_NONE). */
int cvj_member(cvj_value obj, const char *key, cvj_value *out);

/* Element `index` (0-based) of array `arr`; 1 when it exists, else 0. */
int cvj_element(cvj_value arr, size_t index, cvj_value *out);

/* Number of elements of an array (0 for anything else). */
size_t cvj_length(cvj_value arr);

/* Decodes a string value (escapes resolved, \uXXXX as UTF-8) into buf, NUL-terminated.
 * Returns 0, or -1 when v is not a string or does not fit in cap bytes. *outlen (if given)
 * receives the decoded length (a decoded string may contain NUL bytes). */
int cvj_string(cvj_value v, char *buf, size_t cap, size_t *outlen);

/* An integer (a number without fraction or exponent) in [lo, hi]: 0, else -1. */
int cvj_integer(cvj_value v, long long lo, long long hi, long long *out);

/* A boolean: 0 (and *out = 0 or 1), else -1. */
int cvj_boolean(cvj_value v, int *out);

/* A bounded output buffer. On overflow it keeps what fits and sets `overflow`. */
typedef struct {
    char *buf;
    size_t cap;
    size_t len;
    int overflow;
} cvj_writer;

void cvj_init(cvj_writer *w, char *buf, size_t cap);
void cvj_raw(cvj_writer *w, const char *text);     /* text as is (punctuation, keys) */
void cvj_str(cvj_writer *w, const char *s);        /* "s", escaped */
void cvj_int(cvj_writer *w, long long value);      /* a JSON integer */

#endif

/* cvclient.c - a minimal cellvision client in C11 with POSIX sockets, written from
 * protocol/SPEC.md alone: the handshake (§5.1-5.4), one INSPECT with a raw gray8 image (§6.3,
 * §4.2) pipelined with a PING (§5.5, §6.1: answers are matched by request id, in any order),
 * then a graceful CLOSE (§5.6). It prints one line per step; the exit status says how it went
 * (README.md).
 *
 * Build: cc -std=c11 -Wall -Wextra -Werror -pedantic -o cvclient cvclient.c cv_wire.c cv_json.c
 * Add -DCV_MINOR=1 to offer protocol 1.1 instead of 1.0.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <sys/types.h>
#include <unistd.h>

#include "cv_json.h"
#include "cv_wire.h"

#define CV_MAJOR 1
#ifndef CV_MINOR
#define CV_MINOR 0
#endif
#if CV_MINOR < 0 || CV_MINOR > 255
#error "CV_MINOR must be 0..255"
#endif

#define CLIENT_NAME "cellvision-c-example/1.0"
#define PING_DATA "cvclient"

/* Exit statuses (README.md). */
enum {
    EXIT_PASS = 0,        /* the inspection ran and its verdict is pass */
    EXIT_FAIL = 1,        /* the inspection ran and its verdict is fail */
    EXIT_USAGE = 2,       /* bad arguments, token or image */
    EXIT_CONNECTION = 3,  /* could not connect, timed out, or the connection ended early */
    EXIT_PROTOCOL = 4,    /* the server sent something SPEC.md does not allow */
    EXIT_SERVER_ERROR = 5 /* the server answered a request with ERROR */
};

/* ------------------------------------------------------------------------------ options */

typedef struct {
    char host[256];
    char port[16];
    const char *inspection;
    const char *image_file;
    const char *token_file;
    long gray;
    long width;
    long height;
    long timeout_ms;
} options;

static void usage(FILE *out)
{
    fprintf(out,
            "usage: cvclient [options] HOST[:PORT]\n"
            "  --inspection NAME   inspection to run (default brightness)\n"
            "  --width N           image width in pixels (default 64)\n"
            "  --height N          image height in pixels (default 48)\n"
            "  --gray V            fill the gray8 image with V, 0..255 (default 200)\n"
            "  --image FILE        raw gray8 bytes, width*height of them, instead of --gray\n"
            "  --token-file PATH   the server's token, else $CELLVISION_TOKEN or\n"
            "                      $CELLVISION_TOKEN_FILE\n"
            "  --timeout-ms N      give up waiting for an answer after N ms (default 10000)\n"
            "HOST may be [IPv6]; PORT defaults to %d. Exit status: 0 pass, 1 fail, 2 usage,\n"
            "3 connection, 4 protocol error, 5 the server answered ERROR.\n",
            CV_DEFAULT_PORT);
}

static int parse_long(const char *text, long lo, long hi, long *out)
{
    char *end;
    long value;
    errno = 0;
    value = strtol(text, &end, 10);
    if (errno != 0 || end == text || *end != '\0' || value < lo || value > hi) {
        return -1;
    }
    *out = value;
    return 0;
}

static int parse_address(const char *text, options *o)
{
    const char *colon;
    size_t host_len;
    long port = CV_DEFAULT_PORT;
    if (text[0] == '[') {
        const char *close = strchr(text, ']');
        if (close == NULL || (close[1] != '\0' && close[1] != ':')) {
            return -1;
        }
        host_len = (size_t)(close - text - 1);
        memcpy(o->host, text + 1, host_len < sizeof o->host ? host_len : 0);
        colon = close[1] == ':' ? close + 1 : NULL;
    } else {
        colon = strchr(text, ':');
        if (colon != NULL && strchr(colon + 1, ':') != NULL) {
            colon = NULL; /* a bare IPv6 address */
        }
        host_len = colon != NULL ? (size_t)(colon - text) : strlen(text);
        memcpy(o->host, text, host_len < sizeof o->host ? host_len : 0);
    }
    if (host_len == 0 || host_len >= sizeof o->host) {
        return -1;
    }
    o->host[host_len] = '\0';
    if (colon != NULL && parse_long(colon + 1, 1, 65535, &port) != 0) {
        return -1;
    }
    snprintf(o->port, sizeof o->port, "%ld", port);
    return 0;
}

static int parse_options(int argc, char **argv, options *o)
{
    int i;
    const char *address = NULL;
    memset(o, 0, sizeof *o);
    o->inspection = "brightness";
    o->gray = 200;
    o->width = 64;
    o->height = 48;
    o->timeout_ms = 10000;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        int bad = 0;
        if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) {
            usage(stdout);
            exit(EXIT_PASS);
        }
        if (a[0] != '-' || a[1] == '\0') {
            if (address != NULL) {
                fprintf(stderr, "cvclient: more than one address: %s\n", a);
                return -1;
            }
            address = a;
            continue;
        }
        if (v == NULL) {
            fprintf(stderr, "cvclient: %s needs a value\n", a);
            return -1;
        }
        i++;
        if (strcmp(a, "--inspection") == 0) {
            o->inspection = v;
            bad = v[0] == '\0';
        } else if (strcmp(a, "--image") == 0) {
            o->image_file = v;
        } else if (strcmp(a, "--token-file") == 0) {
            o->token_file = v;
        } else if (strcmp(a, "--gray") == 0) {
            bad = parse_long(v, 0, 255, &o->gray);
        } else if (strcmp(a, "--width") == 0) {
            bad = parse_long(v, 1, 65535, &o->width);
        } else if (strcmp(a, "--height") == 0) {
            bad = parse_long(v, 1, 65535, &o->height);
        } else if (strcmp(a, "--timeout-ms") == 0) {
            bad = parse_long(v, 1, 86400000L, &o->timeout_ms);
        } else {
            fprintf(stderr, "cvclient: unknown option %s\n", a);
            return -1;
        }
        if (bad) {
            fprintf(stderr, "cvclient: bad value for %s: %s\n", a, v);
            return -1;
        }
    }
    if (address == NULL) {
        fprintf(stderr, "cvclient: give the server's HOST[:PORT]\n");
        return -1;
    }
    if (parse_address(address, o) != 0) {
        fprintf(stderr, "cvclient: bad server address %s\n", address);
        return -1;
    }
    return 0;
}

/* ------------------------------------------------------------------------------ token, image */

/* Reads a whole small file into buf (NUL-terminated); its length, or -1. */
static long read_file(const char *path, char *buf, size_t cap)
{
    FILE *f = fopen(path, "rb");
    size_t n;
    if (f == NULL) {
        return -1;
    }
    n = fread(buf, 1, cap - 1, f);
    if (ferror(f) || (n == cap - 1 && fgetc(f) != EOF)) {
        fclose(f);
        return -1;
    }
    fclose(f);
    buf[n] = '\0';
    return (long)n;
}

/* Whitespace around a token (a file's final newline) is never part of it. */
static char *trim(char *s)
{
    char *end;
    while (*s == ' ' || *s == '\t' || *s == '\r' || *s == '\n') {
        s++;
    }
    end = s + strlen(s);
    while (end > s && (end[-1] == ' ' || end[-1] == '\t' || end[-1] == '\r' || end[-1] == '\n')) {
        *--end = '\0';
    }
    return s;
}

/* The token from --token-file, else $CELLVISION_TOKEN, else the file $CELLVISION_TOKEN_FILE
 * names (the rule of the project's own tools). *token is NULL when none is given; -1 on an
 * error (an empty token is an error, never "no token"). */
static int find_token(const options *o, char *buf, size_t cap, const char **token)
{
    const char *env = getenv("CELLVISION_TOKEN");
    const char *env_file = getenv("CELLVISION_TOKEN_FILE");
    const char *file = o->token_file;
    const char *source;
    *token = NULL;
    if (file == NULL && env != NULL && env_file != NULL) {
        fprintf(stderr, "cvclient: set $CELLVISION_TOKEN or $CELLVISION_TOKEN_FILE, not both\n");
        return -1;
    }
    if (file == NULL && env != NULL) {
        snprintf(buf, cap, "%s", env);
        source = "$CELLVISION_TOKEN";
    } else {
        if (file == NULL) {
            file = env_file;
        }
        if (file == NULL) {
            return 0;
        }
        if (read_file(file, buf, cap) < 0) {
            fprintf(stderr, "cvclient: cannot read the token file %s\n", file);
            return -1;
        }
        source = "the token file";
    }
    *token = trim(buf);
    if ((*token)[0] == '\0') {
        fprintf(stderr, "cvclient: %s gives an empty token\n", source);
        return -1;
    }
    return 0;
}

static unsigned char *make_image(const options *o)
{
    size_t size = (size_t)o->width * (size_t)o->height;
    unsigned char *pixels = malloc(size);
    FILE *f;
    if (pixels == NULL) {
        fprintf(stderr, "cvclient: out of memory for a %ldx%ld image\n", o->width, o->height);
        return NULL;
    }
    if (o->image_file == NULL) {
        memset(pixels, (int)o->gray, size);
        return pixels;
    }
    f = fopen(o->image_file, "rb");
    if (f == NULL || fread(pixels, 1, size, f) != size || fgetc(f) != EOF) {
        fprintf(stderr, "cvclient: %s must hold exactly %ldx%ld = %zu bytes of gray8\n",
                o->image_file, o->width, o->height, size);
        if (f != NULL) {
            fclose(f);
        }
        free(pixels);
        return NULL;
    }
    fclose(f);
    return pixels;
}

/* ------------------------------------------------------------------------------ session */

typedef struct {
    uint32_t id;
    uint16_t type; /* the request's message type */
    int answered;
} request;

typedef struct {
    int fd;
    int open;      /* WELCOME received: the agreed version is in major/minor */
    int closed;    /* the connection is over (CLOSE or a fatal error) */
    uint8_t major; /* version in the headers we send */
    uint8_t minor;
    request pending[4];
    size_t npending;
    int outcome;
    long long max_image_pixels; /* from WELCOME's limits, -1 when not announced */
    long long max_frame_bytes;
} session;

/* Keeps the most serious outcome: connection > protocol > server error > fail > pass. */
static void worsen(session *s, int code)
{
    static const int rank[] = {0, 1, 5, 4, 3, 2}; /* indexed by exit status 0..5 */
    if (rank[code] > rank[s->outcome]) {
        s->outcome = code;
    }
}

/* Prints text as a quoted string: '"', '\' and control characters escaped, UTF-8 as is. */
static void print_quoted(const char *text, size_t n)
{
    size_t i;
    putchar('"');
    for (i = 0; i < n; i++) {
        unsigned char ch = (unsigned char)text[i];
        if (ch == '"' || ch == '\\') {
            printf("\\%c", ch);
        } else if (ch == '\n') {
            fputs("\\n", stdout);
        } else if (ch == '\t') {
            fputs("\\t", stdout);
        } else if (ch == '\r') {
            fputs("\\r", stdout);
        } else if (ch < 0x20 || ch == 0x7F) {
            printf("\\x%02x", ch);
        } else {
            putchar(ch);
        }
    }
    putchar('"');
}

/* Prints member `key` of obj as ` label="..."` when it is a string. */
static void print_labelled(cvj_value obj, const char *key, const char *label)
{
    cvj_value v;
    char text[4096];
    size_t n;
    if (cvj_member(obj, key, &v) && cvj_string(v, text, sizeof text, &n) == 0) {
        printf(" %s=", label);
        print_quoted(text, n);
    }
}

static void print_string_member(cvj_value obj, const char *key)
{
    print_labelled(obj, key, key);
}

static void send_fatal_error(session *s, uint32_t id, int code, const char *name, const char *why)
{
    char meta[512];
    char err[128];
    cvj_writer w;
    cvj_init(&w, meta, sizeof meta);
    cvj_raw(&w, "{\"code\":");
    cvj_int(&w, code);
    cvj_raw(&w, ",\"name\":");
    cvj_str(&w, name);
    cvj_raw(&w, ",\"message\":");
    cvj_str(&w, why);
    cvj_raw(&w, ",\"fatal\":true}");
    if (!w.overflow) {
        cv_send_frame(s->fd, s->major, s->minor, CV_ERROR, id, meta, w.len, NULL, 0, err,
                      sizeof err);
    }
    s->closed = 1;
}

static request *find_pending(session *s, uint32_t id)
{
    size_t i;
    for (i = 0; i < s->npending; i++) {
        if (s->pending[i].id == id && !s->pending[i].answered) {
            return &s->pending[i];
        }
    }
    return NULL;
}

static size_t unanswered(const session *s)
{
    size_t i, n = 0;
    for (i = 0; i < s->npending; i++) {
        n += !s->pending[i].answered;
    }
    return n;
}

static int answers(uint16_t request_type, uint16_t type)
{
    switch (request_type) {
    case CV_HELLO: return type == CV_WELCOME;
    case CV_PING: return type == CV_PONG;
    case CV_INSPECT: return type == CV_RESULT;
    default: return 0;
    }
}

static void on_welcome(session *s, const cv_frame *f, cvj_value meta)
{
    cvj_value version, major, minor, limits, v;
    long long maj = -1, min = -1, value;
    if (!cvj_member(meta, "version", &version) || version.kind != CVJ_ARRAY ||
        cvj_length(version) != 2 || !cvj_element(version, 0, &major) ||
        !cvj_element(version, 1, &minor) || cvj_integer(major, 0, 255, &maj) != 0 ||
        cvj_integer(minor, 0, 255, &min) != 0) {
        printf("protocol error: WELCOME id=%lu has no valid version [major, minor]\n",
               (unsigned long)f->h.request_id);
        worsen(s, EXIT_PROTOCOL);
        send_fatal_error(s, 0, 5, "BAD_METADATA", "WELCOME without a valid version");
        return;
    }
    if (maj != CV_MAJOR) {
        /* SPEC §5.3: refuse a WELCOME whose version the client does not speak. */
        printf("protocol error: WELCOME agrees on version %lld.%lld, this client speaks %d.x\n",
               maj, min, CV_MAJOR);
        worsen(s, EXIT_PROTOCOL);
        send_fatal_error(s, 0, 2, "UNSUPPORTED_VERSION", "the client speaks major version 1");
        return;
    }
    s->open = 1;
    s->major = (uint8_t)maj;
    s->minor = (uint8_t)min; /* any minor of major 1: §8 makes them interoperate */
    if (cvj_member(meta, "limits", &limits)) {
        if (cvj_member(limits, "max_image_pixels", &v) &&
            cvj_integer(v, 1, 1LL << 53, &value) == 0) {
            s->max_image_pixels = value;
        }
        if (cvj_member(limits, "max_frame_bytes", &v) &&
            cvj_integer(v, 1, 1LL << 53, &value) == 0) {
            s->max_frame_bytes = value;
        }
    }
    printf("welcome id=%lu version=%u.%u", (unsigned long)f->h.request_id, s->major, s->minor);
    if (cvj_member(meta, "server", &v)) {
        print_labelled(v, "name", "server");
    }
    printf("\n");
}

static void on_pong(session *s, const cv_frame *f, cvj_value meta)
{
    cvj_value v;
    char data[64];
    if (!cvj_member(meta, "data", &v) || cvj_string(v, data, sizeof data, NULL) != 0 ||
        strcmp(data, PING_DATA) != 0) {
        printf("protocol error: PONG id=%lu does not echo the PING's data\n",
               (unsigned long)f->h.request_id);
        worsen(s, EXIT_PROTOCOL);
        return;
    }
    printf("pong id=%lu data=\"%s\"\n", (unsigned long)f->h.request_id, data);
}

static void on_result(session *s, const cv_frame *f, cvj_value meta)
{
    cvj_value v;
    char verdict[8];
    int stored;
    if (!cvj_member(meta, "verdict", &v) || cvj_string(v, verdict, sizeof verdict, NULL) != 0 ||
        (strcmp(verdict, "pass") != 0 && strcmp(verdict, "fail") != 0)) {
        printf("protocol error: RESULT id=%lu has no verdict \"pass\" or \"fail\"\n",
               (unsigned long)f->h.request_id);
        worsen(s, EXIT_PROTOCOL);
        return;
    }
    printf("result id=%lu", (unsigned long)f->h.request_id);
    print_string_member(meta, "inspection");
    printf(" verdict=%s", verdict);
    if (cvj_member(meta, "stored", &v) && cvj_boolean(v, &stored) == 0) {
        printf(" stored=%s", stored ? "true" : "false");
    }
    printf("\n");
    worsen(s, strcmp(verdict, "pass") == 0 ? EXIT_PASS : EXIT_FAIL);
}

static void on_error(session *s, const cv_frame *f, cvj_value meta)
{
    cvj_value v;
    long long code = -1;
    int fatal = 0;
    request *r = find_pending(s, f->h.request_id);
    if (!cvj_member(meta, "code", &v) || cvj_integer(v, 0, 0xFFFF, &code) != 0) {
        printf("protocol error: ERROR id=%lu without an integer code\n",
               (unsigned long)f->h.request_id);
        worsen(s, EXIT_PROTOCOL);
    }
    if (cvj_member(meta, "fatal", &v)) {
        cvj_boolean(v, &fatal); /* SPEC §7: default false, authoritative when present */
    }
    printf("error id=%lu code=%lld", (unsigned long)f->h.request_id, code);
    print_string_member(meta, "name");
    printf(" fatal=%s", fatal ? "true" : "false");
    print_string_member(meta, "message");
    printf("\n");
    if (r != NULL) {
        r->answered = 1;
        worsen(s, EXIT_SERVER_ERROR);
    } else if (f->h.request_id != 0) {
        printf("warning: the ERROR answers no request in flight\n");
    } else {
        worsen(s, EXIT_SERVER_ERROR); /* about the connection itself */
    }
    if (fatal) {
        s->closed = 1; /* the server closes the connection after a fatal ERROR */
    }
}

/* Handles one frame from the server. */
static void dispatch(session *s, const cv_frame *f)
{
    char name_buf[16], err[128];
    const char *name = cv_type_name(f->h.type, name_buf, sizeof name_buf);
    const char *text = f->h.meta_len > 0 ? (const char *)f->body : "{}";
    size_t len = f->h.meta_len > 0 ? f->h.meta_len : 2;
    cvj_value meta;
    request *r;
    if (s->open && f->h.major != s->major && f->h.type != CV_ERROR) {
        printf("protocol error: %s id=%lu carries version %u.%u, agreed %u.%u\n", name,
               (unsigned long)f->h.request_id, f->h.major, f->h.minor, s->major, s->minor);
        worsen(s, EXIT_PROTOCOL);
        send_fatal_error(s, f->h.request_id, 2, "UNSUPPORTED_VERSION", "wrong major version");
        return;
    }
    if (cvj_parse(text, len, &meta, err, sizeof err) != 0 || meta.kind != CVJ_OBJECT) {
        printf("protocol error: %s id=%lu: metadata is not a JSON object (%s)\n", name,
               (unsigned long)f->h.request_id, meta.kind != CVJ_OBJECT ? "not an object" : err);
        r = find_pending(s, f->h.request_id);
        if (r != NULL) {
            r->answered = 1; /* that request has failed */
        }
        worsen(s, EXIT_PROTOCOL);
        return;
    }
    if (f->h.type == CV_CLOSE) {
        printf("close received");
        print_string_member(meta, "reason");
        printf("\n");
        if (unanswered(s) > 0) {
            printf("error: %zu requests in flight failed: the server closed the connection\n",
                   unanswered(s));
            worsen(s, EXIT_CONNECTION);
        }
        s->closed = 1;
        return;
    }
    if (f->h.type == CV_ERROR) {
        on_error(s, f, meta);
        return;
    }
    r = find_pending(s, f->h.request_id);
    if (r == NULL || !answers(r->type, f->h.type)) {
        /* SPEC §5.7: report UNEXPECTED_MESSAGE and go on; a request whose id it carried has
         * failed. */
        printf("unexpected: %s id=%lu answers no request in flight\n", name,
               (unsigned long)f->h.request_id);
        if (r != NULL) {
            r->answered = 1;
            worsen(s, EXIT_PROTOCOL);
        }
        return;
    }
    r->answered = 1;
    switch (f->h.type) {
    case CV_WELCOME: on_welcome(s, f, meta); break;
    case CV_PONG: on_pong(s, f, meta); break;
    case CV_RESULT: on_result(s, f, meta); break;
    default: break;
    }
}

/* Reads and handles frames until every request is answered or the connection is over. */
static void await_answers(session *s)
{
    while (!s->closed && unanswered(s) > 0) {
        cv_frame f;
        char err[160];
        cv_status st = cv_recv_frame(s->fd, &f, err, sizeof err);
        if (st == CV_END) {
            printf("error: the server ended the connection with %zu requests in flight\n",
                   unanswered(s));
            worsen(s, EXIT_CONNECTION);
            s->closed = 1;
            return;
        }
        if (st == CV_IO_ERROR) {
            printf("error: %s\n", err);
            worsen(s, EXIT_CONNECTION);
            s->closed = 1;
            return;
        }
        if (st == CV_MALFORMED) {
            printf("protocol error: %s\n", err);
            worsen(s, EXIT_PROTOCOL);
            send_fatal_error(s, 0, 1, "MALFORMED_FRAME", err);
            return;
        }
        dispatch(s, &f);
        cv_frame_free(&f);
    }
}

static int send_request(session *s, uint16_t type, uint32_t id, const char *meta, size_t len,
                        const cv_blob *blobs, size_t nblobs)
{
    char err[160];
    if (cv_send_frame(s->fd, s->major, s->minor, type, id, meta, len, blobs, nblobs, err,
                      sizeof err) != CV_OK) {
        printf("error: %s\n", err);
        worsen(s, EXIT_CONNECTION);
        s->closed = 1;
        return -1;
    }
    if (type != CV_CLOSE) {
        request *r = &s->pending[s->npending++];
        r->id = id;
        r->type = type;
        r->answered = 0;
    }
    return 0;
}

/* ------------------------------------------------------------------------------ steps */

static int connect_to(const options *o)
{
    struct addrinfo hints, *found, *ai;
    struct timeval tv;
    int fd = -1, rc, one = 1;
    memset(&hints, 0, sizeof hints);
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    rc = getaddrinfo(o->host, o->port, &hints, &found);
    if (rc != 0) {
        printf("error: cannot resolve %s: %s\n", o->host, gai_strerror(rc));
        return -1;
    }
    for (ai = found; ai != NULL; ai = ai->ai_next) {
        fd = socket(ai->ai_family, ai->ai_socktype, ai->ai_protocol);
        if (fd < 0) {
            continue;
        }
        if (connect(fd, ai->ai_addr, ai->ai_addrlen) == 0) {
            break;
        }
        close(fd);
        fd = -1;
    }
    freeaddrinfo(found);
    if (fd < 0) {
        printf("error: cannot connect to %s port %s: %s\n", o->host, o->port, strerror(errno));
        return -1;
    }
    tv.tv_sec = o->timeout_ms / 1000;
    tv.tv_usec = (o->timeout_ms % 1000) * 1000;
    setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv);
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one); /* small requests go at once */
    return fd;
}

static int handshake(session *s, const char *token)
{
    char meta[8192];
    cvj_writer w;
    cvj_init(&w, meta, sizeof meta);
    cvj_raw(&w, "{\"versions\":[[");
    cvj_int(&w, CV_MAJOR);
    cvj_raw(&w, ",");
    cvj_int(&w, CV_MINOR);
    cvj_raw(&w, "]],\"client\":");
    cvj_str(&w, CLIENT_NAME);
    cvj_raw(&w, ",\"max_frame_bytes\":");
    cvj_int(&w, (long long)CV_MAX_FRAME_BYTES);
    if (token != NULL) {
        cvj_raw(&w, ",\"auth_token\":");
        cvj_str(&w, token);
    }
    cvj_raw(&w, "}");
    if (w.overflow) {
        fprintf(stderr, "cvclient: the token is too long\n");
        worsen(s, EXIT_USAGE);
        return -1;
    }
    /* SPEC §5.1: the HELLO header carries the newest version the client speaks. */
    printf("hello id=1 versions=[[%d,%d]] token=%s\n", CV_MAJOR, CV_MINOR, token ? "yes" : "no");
    if (send_request(s, CV_HELLO, 1, meta, w.len, NULL, 0) != 0) {
        return -1;
    }
    await_answers(s);
    return s->open && !s->closed ? 0 : -1;
}

static void inspect_and_ping(session *s, const options *o, const unsigned char *pixels)
{
    char meta[1024];
    cvj_writer w;
    cv_blob blob;
    long long pixels_n = (long long)o->width * o->height;
    blob.data = pixels;
    blob.len = (uint32_t)pixels_n;
    cvj_init(&w, meta, sizeof meta);
    cvj_raw(&w, "{\"inspection\":");
    cvj_str(&w, o->inspection);
    cvj_raw(&w, ",\"images\":[{\"blob\":0,\"encoding\":\"gray8\",\"width\":");
    cvj_int(&w, o->width);
    cvj_raw(&w, ",\"height\":");
    cvj_int(&w, o->height);
    cvj_raw(&w, ",\"role\":\"color\"}]}");
    if (w.overflow) {
        fprintf(stderr, "cvclient: the inspection name is too long\n");
        worsen(s, EXIT_USAGE);
        return;
    }
    /* SPEC §3.4: a client MUST NOT exceed the limits the server announced. */
    if (s->max_image_pixels > 0 && pixels_n > s->max_image_pixels) {
        fprintf(stderr, "cvclient: %lldx%lld pixels exceed the server's max_image_pixels %lld\n",
                (long long)o->width, (long long)o->height, s->max_image_pixels);
        worsen(s, EXIT_USAGE);
        return;
    }
    if (s->max_frame_bytes > 0 && CV_HEADER_SIZE + (long long)w.len + 4 + pixels_n >
                                      s->max_frame_bytes) {
        fprintf(stderr, "cvclient: the INSPECT frame exceeds the server's max_frame_bytes\n");
        worsen(s, EXIT_USAGE);
        return;
    }
    /* Pipelined (SPEC §6.1): both go out before either answer is read; the answers are
     * matched by request id, whatever their order. */
    printf("inspect id=2 inspection=");
    print_quoted(o->inspection, strlen(o->inspection));
    printf(" image=gray8 %ldx%ld\n", o->width, o->height);
    if (send_request(s, CV_INSPECT, 2, meta, w.len, &blob, 1) != 0) {
        return;
    }
    printf("ping id=3\n");
    if (send_request(s, CV_PING, 3, "{\"data\":\"" PING_DATA "\"}",
                     strlen("{\"data\":\"" PING_DATA "\"}"), NULL, 0) != 0) {
        return;
    }
    await_answers(s);
}

/* SPEC §5.6: CLOSE, then read until the server's CLOSE, then close the socket. */
static void close_gracefully(session *s)
{
    static const char meta[] = "{\"reason\":\"done\"}";
    if (send_request(s, CV_CLOSE, 0, meta, sizeof meta - 1, NULL, 0) != 0) {
        return;
    }
    printf("close sent\n");
    while (!s->closed) {
        cv_frame f;
        char err[160];
        cv_status st = cv_recv_frame(s->fd, &f, err, sizeof err);
        if (st != CV_OK) {
            printf("error: no CLOSE from the server: %s\n",
                   st == CV_END ? "the connection ended" : err);
            worsen(s, st == CV_MALFORMED ? EXIT_PROTOCOL : EXIT_CONNECTION);
            return;
        }
        dispatch(s, &f);
        cv_frame_free(&f);
    }
}

int main(int argc, char **argv)
{
    options o;
    session s;
    char token_buf[4096];
    const char *token;
    unsigned char *pixels;
    if (parse_options(argc, argv, &o) != 0) {
        usage(stderr);
        return EXIT_USAGE;
    }
    if (find_token(&o, token_buf, sizeof token_buf, &token) != 0) {
        return EXIT_USAGE;
    }
    pixels = make_image(&o);
    if (pixels == NULL) {
        return EXIT_USAGE;
    }
    signal(SIGPIPE, SIG_IGN); /* a closed socket is an error to report, not a signal */
    setvbuf(stdout, NULL, _IOLBF, 0);
    memset(&s, 0, sizeof s);
    s.major = CV_MAJOR;
    s.minor = CV_MINOR;
    s.max_image_pixels = -1;
    s.max_frame_bytes = -1;
    s.outcome = EXIT_PASS;
    s.fd = connect_to(&o);
    if (s.fd < 0) {
        free(pixels);
        printf("exit %d\n", EXIT_CONNECTION);
        return EXIT_CONNECTION;
    }
    printf("connected %s port %s\n", o.host, o.port);
    if (handshake(&s, token) == 0) {
        inspect_and_ping(&s, &o, pixels);
        if (!s.closed) {
            close_gracefully(&s);
        }
    } else if (s.outcome == EXIT_PASS) {
        worsen(&s, EXIT_CONNECTION);
    }
    close(s.fd);
    free(pixels);
    printf("exit %d\n", s.outcome);
    return s.outcome;
}

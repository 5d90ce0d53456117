/* cv_wire.c - see cv_wire.h. Written from SPEC.md §3. */
#define _POSIX_C_SOURCE 200809L
#include "cv_wire.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/types.h>

static const unsigned char MAGIC[4] = {0x43, 0x56, 0x49, 0x53}; /* "CVIS" */

static void put_u16(unsigned char *p, uint16_t v)
{
    p[0] = (unsigned char)(v & 0xFFu);
    p[1] = (unsigned char)(v >> 8);
}

static void put_u32(unsigned char *p, uint32_t v)
{
    p[0] = (unsigned char)(v & 0xFFu);
    p[1] = (unsigned char)((v >> 8) & 0xFFu);
    p[2] = (unsigned char)((v >> 16) & 0xFFu);
    p[3] = (unsigned char)(v >> 24);
}

static uint16_t get_u16(const unsigned char *p)
{
    return (uint16_t)(p[0] | (p[1] << 8));
}

static uint32_t get_u32(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

void cv_header_pack(const cv_header *h, unsigned char out[CV_HEADER_SIZE])
{
    memcpy(out, MAGIC, 4);
    out[4] = h->major;
    out[5] = h->minor;
    put_u16(out + 6, h->type);
    put_u16(out + 8, h->flags);
    put_u16(out + 10, h->blob_count);
    put_u32(out + 12, h->request_id);
    put_u32(out + 16, h->meta_len);
    put_u32(out + 20, h->body_len);
}

int cv_header_unpack(const unsigned char in[CV_HEADER_SIZE], cv_header *h)
{
    if (memcmp(in, MAGIC, 4) != 0) {
        return -1;
    }
    h->major = in[4];
    h->minor = in[5];
    h->type = get_u16(in + 6);
    h->flags = get_u16(in + 8);
    h->blob_count = get_u16(in + 10);
    h->request_id = get_u32(in + 12);
    h->meta_len = get_u32(in + 16);
    h->body_len = get_u32(in + 20);
    return 0;
}

static void set_err(char *err, size_t errcap, const char *what, const char *detail)
{
    if (errcap > 0) {
        snprintf(err, errcap, "%s%s%s", what, detail[0] ? ": " : "", detail);
    }
}

static cv_status send_all(int fd, const void *data, size_t len, char *err, size_t errcap)
{
    const unsigned char *p = data;
    while (len > 0) {
        ssize_t n = send(fd, p, len, 0);
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            set_err(err, errcap, "send failed", strerror(errno));
            return CV_IO_ERROR;
        }
        p += n;
        len -= (size_t)n;
    }
    return CV_OK;
}

/* Reads exactly len bytes. *got says how many arrived before an end of stream. */
static cv_status recv_all(int fd, void *data, size_t len, size_t *got, char *err, size_t errcap)
{
    unsigned char *p = data;
    *got = 0;
    while (*got < len) {
        ssize_t n = recv(fd, p + *got, len - *got, 0);
        if (n == 0) {
            return CV_END;
        }
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            set_err(err, errcap,
                    errno == EAGAIN || errno == EWOULDBLOCK ? "no answer in time" : "recv failed",
                    errno == EAGAIN || errno == EWOULDBLOCK ? "" : strerror(errno));
            return CV_IO_ERROR;
        }
        *got += (size_t)n;
    }
    return CV_OK;
}

cv_status cv_send_frame(int fd, uint8_t major, uint8_t minor, uint16_t type, uint32_t request_id,
                        const char *meta, size_t meta_len, const cv_blob *blobs, size_t nblobs,
                        char *err, size_t errcap)
{
    unsigned char header[CV_HEADER_SIZE];
    unsigned char table[4 * CV_MAX_BLOBS];
    uint64_t body = meta_len + 4u * (uint64_t)nblobs;
    cv_header h;
    size_t i;
    cv_status st;
    if (nblobs > CV_MAX_BLOBS) {
        set_err(err, errcap, "too many blobs", "");
        return CV_MALFORMED;
    }
    for (i = 0; i < nblobs; i++) {
        put_u32(table + 4 * i, blobs[i].len);
        body += blobs[i].len;
    }
    if (body > UINT32_MAX - CV_HEADER_SIZE) {
        set_err(err, errcap, "frame too large", "");
        return CV_MALFORMED;
    }
    h.major = major;
    h.minor = minor;
    h.type = type;
    h.flags = 0; /* SPEC §3.5: no flag is defined in version 1 */
    h.blob_count = (uint16_t)nblobs;
    h.request_id = request_id;
    h.meta_len = (uint32_t)meta_len;
    h.body_len = (uint32_t)body;
    cv_header_pack(&h, header);
    if ((st = send_all(fd, header, sizeof header, err, errcap)) != CV_OK ||
        (st = send_all(fd, meta, meta_len, err, errcap)) != CV_OK ||
        (st = send_all(fd, table, 4 * nblobs, err, errcap)) != CV_OK) {
        return st;
    }
    for (i = 0; i < nblobs; i++) {
        if ((st = send_all(fd, blobs[i].data, blobs[i].len, err, errcap)) != CV_OK) {
            return st;
        }
    }
    return CV_OK;
}

cv_status cv_recv_frame(int fd, cv_frame *frame, char *err, size_t errcap)
{
    unsigned char header[CV_HEADER_SIZE];
    cv_header *h = &frame->h;
    uint64_t sum;
    size_t got, i;
    cv_status st;
    frame->body = NULL;
    st = recv_all(fd, header, sizeof header, &got, err, errcap);
    if (st == CV_END) {
        if (got == 0) {
            return CV_END; /* between two frames: an end of stream, not a broken frame */
        }
        set_err(err, errcap, "the connection ended inside a frame header", "");
        return CV_MALFORMED;
    }
    if (st != CV_OK) {
        return st;
    }
    if (cv_header_unpack(header, h) != 0) {
        set_err(err, errcap, "bad magic: not a cellvision frame", "");
        return CV_MALFORMED;
    }
    /* SPEC §3.1: check the header before reading (or allocating for) the body. */
    if ((uint64_t)h->body_len + CV_HEADER_SIZE > CV_MAX_FRAME_BYTES) {
        set_err(err, errcap, "frame larger than this client accepts", "");
        return CV_MALFORMED;
    }
    if (h->meta_len > CV_MAX_METADATA_BYTES) {
        set_err(err, errcap, "metadata larger than this client accepts", "");
        return CV_MALFORMED;
    }
    if (h->blob_count > CV_MAX_BLOBS) {
        set_err(err, errcap, "more blobs than this client accepts", "");
        return CV_MALFORMED;
    }
    if ((uint64_t)h->meta_len + 4u * (uint64_t)h->blob_count > h->body_len) {
        set_err(err, errcap, "metadata and blob table longer than the body", "");
        return CV_MALFORMED;
    }
    if (h->body_len > 0) {
        frame->body = malloc(h->body_len);
        if (frame->body == NULL) {
            set_err(err, errcap, "out of memory", "");
            return CV_IO_ERROR;
        }
        st = recv_all(fd, frame->body, h->body_len, &got, err, errcap);
        if (st != CV_OK) {
            if (st == CV_END) {
                set_err(err, errcap, "the connection ended inside a frame", "");
                st = CV_MALFORMED;
            }
            cv_frame_free(frame);
            return st;
        }
    }
    /* SPEC §3.3: the blob lengths must add up to the body length. */
    sum = (uint64_t)h->meta_len + 4u * (uint64_t)h->blob_count;
    for (i = 0; i < h->blob_count; i++) {
        sum += get_u32(frame->body + h->meta_len + 4 * i);
    }
    if (sum != h->body_len) {
        set_err(err, errcap, "blob lengths do not add up to the body length", "");
        cv_frame_free(frame);
        return CV_MALFORMED;
    }
    return CV_OK;
}

void cv_frame_free(cv_frame *frame)
{
    free(frame->body);
    frame->body = NULL;
}

const char *cv_type_name(uint16_t type, char *buf, size_t cap)
{
    switch (type) {
    case CV_HELLO: return "HELLO";
    case CV_WELCOME: return "WELCOME";
    case CV_PING: return "PING";
    case CV_PONG: return "PONG";
    case CV_CLOSE: return "CLOSE";
    case CV_LIST_INSPECTIONS: return "LIST_INSPECTIONS";
    case CV_INSPECTIONS: return "INSPECTIONS";
    case CV_INSPECT: return "INSPECT";
    case CV_RESULT: return "RESULT";
    case CV_CAPTURE: return "CAPTURE";
    case CV_FRAMES: return "FRAMES";
    case CV_RELOAD: return "RELOAD";
    case CV_RELOADED: return "RELOADED";
    case CV_ERROR: return "ERROR";
    default:
        snprintf(buf, cap, "type 0x%04x", (unsigned)type);
        return buf;
    }
}

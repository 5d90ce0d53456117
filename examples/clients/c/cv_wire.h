/* cv_wire.h - cellvision frames on a blocking socket (SPEC.md §3).
 *
 * Every multi-byte integer on the wire is little-endian; the header is packed and unpacked
 * byte by byte, so the code is the same on big- and little-endian hosts.
 */
#ifndef CV_WIRE_H
#define CV_WIRE_H

#include <stddef.h>
#include <stdint.h>

#define CV_HEADER_SIZE 24
#define CV_DEFAULT_PORT 7878

/* Message types (SPEC §3.1). */
enum {
    CV_HELLO = 0x0001,
    CV_WELCOME = 0x0002,
    CV_PING = 0x0003,
    CV_PONG = 0x0004,
    CV_CLOSE = 0x0005,
    CV_LIST_INSPECTIONS = 0x0010,
    CV_INSPECTIONS = 0x0011,
    CV_INSPECT = 0x0020,
    CV_RESULT = 0x0021,
    CV_CAPTURE = 0x0030,
    CV_FRAMES = 0x0031,
    CV_RELOAD = 0x0040,
    CV_RELOADED = 0x0041,
    CV_ERROR = 0x00FF
};

/* The limits this client applies to what the server sends (SPEC §3.4). It announces the frame
 * size in HELLO (max_frame_bytes); the others are the protocol's defaults. */
#define CV_MAX_FRAME_BYTES (16u * 1024u * 1024u)
#define CV_MAX_METADATA_BYTES (1024u * 1024u)
#define CV_MAX_BLOBS 64u

typedef struct {
    uint8_t major;
    uint8_t minor;
    uint16_t type;
    uint16_t flags;
    uint16_t blob_count;
    uint32_t request_id;
    uint32_t meta_len;
    uint32_t body_len;
} cv_header;

/* A received frame: the header and its body (metadata, blob table, blobs). */
typedef struct {
    cv_header h;
    unsigned char *body; /* h.body_len bytes, malloc'ed; NULL when the body is empty */
} cv_frame;

/* One blob to send. */
typedef struct {
    const void *data;
    uint32_t len;
} cv_blob;

typedef enum {
    CV_OK = 0,
    CV_END,       /* the peer closed the connection between two frames */
    CV_IO_ERROR,  /* the socket failed or timed out */
    CV_MALFORMED  /* the bytes are not a valid frame (SPEC: MALFORMED_FRAME, FRAME_TOO_LARGE) */
} cv_status;

void cv_header_pack(const cv_header *h, unsigned char out[CV_HEADER_SIZE]);

/* 0, or -1 when the magic is not "CVIS". */
int cv_header_unpack(const unsigned char in[CV_HEADER_SIZE], cv_header *h);

/* Sends one frame: metadata (UTF-8 JSON, meta_len bytes) and nblobs blobs. */
cv_status cv_send_frame(int fd, uint8_t major, uint8_t minor, uint16_t type, uint32_t request_id,
                        const char *meta, size_t meta_len, const cv_blob *blobs, size_t nblobs,
                        char *err, size_t errcap);

/* Receives one frame, checking the header (magic, limits, lengths) before reading the body and
 * the blob table after it. On CV_OK the caller frees with cv_frame_free(). */
cv_status cv_recv_frame(int fd, cv_frame *frame, char *err, size_t errcap);

void cv_frame_free(cv_frame *frame);

/* Message type name for printing ("type 0x1234" for unknown ones; buf holds at least 16). */
const char *cv_type_name(uint16_t type, char *buf, size_t cap);

#endif

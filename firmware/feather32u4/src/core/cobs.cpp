// cobs.cpp -- COBS encoder and incremental decoder (see cobs.h).
#include "cobs.h"

namespace stipi {

uint16_t cobs_encode(const uint8_t* in, uint16_t len, uint8_t* out) {
  uint16_t code_pos = 0;
  uint8_t code = 1;
  uint16_t o = 1;
  for (uint16_t i = 0; i < len; ++i) {
    if (in[i] == 0) {
      out[code_pos] = code;
      code_pos = o++;
      code = 1;
    } else {
      out[o++] = in[i];
      ++code;
      if (code == 0xFF && i + 1 < len) {
        out[code_pos] = code;
        code_pos = o++;
        code = 1;
      }
    }
  }
  out[code_pos] = code;
  return o;
}

void CobsDecoder::reset() {
  len_ = 0;
  remaining_ = 0;
  code_ = 0;
  overflow_ = false;
}

CobsDecoder::Result CobsDecoder::feed(uint8_t byte) {
  if (byte == 0) {
    const bool started = code_ != 0 || overflow_;
    const bool valid = !overflow_ && remaining_ == 0;
    const uint8_t n = len_;
    const bool overflow_was = overflow_;
    reset();
    len_ = n;
    if (!started) {
      len_ = 0;
      return kNone;  // empty frame (two delimiters in a row): ignored
    }
    if (!valid) {
      const bool overlong = overflow_was;
      len_ = 0;
      return overlong ? kOverlong : kError;
    }
    return kFrame;
  }
  if (overflow_) return kNone;
  if (remaining_ == 0) {
    // A code byte. The previous block (if any, and if shorter than 254 data bytes) implies a 0.
    if (code_ == 0) {
      len_ = 0;  // first code byte of a new frame
    } else if (code_ != 0xFF) {
      if (len_ >= kMaxFrameLen) {
        overflow_ = true;
        return kNone;
      }
      buf_[len_++] = 0;
    }
    code_ = byte;
    remaining_ = static_cast<uint8_t>(byte - 1);
    return kNone;
  }
  if (len_ >= kMaxFrameLen) {
    overflow_ = true;
    return kNone;
  }
  buf_[len_++] = byte;
  --remaining_;
  return kNone;
}

}  // namespace stipi

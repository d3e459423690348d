// cobs.h -- Consistent Overhead Byte Stuffing (Cheshire & Baker 1999) for the wire framing.
//
// Owns: encoding a frame into COBS (no 0x00 in the output) and an incremental, bounded decoder
// fed one byte at a time that yields whole frames at each 0x00 delimiter. Does not know about
// headers or CRCs (frame.h does).
#ifndef STIPI_CORE_COBS_H
#define STIPI_CORE_COBS_H

#include <stdint.h>

namespace stipi {

// Largest decoded frame the protocol allows: header 8 + body 64 + crc 2 [B].
const uint8_t kMaxFrameLen = 74;
// COBS adds one byte per 254 data bytes (plus one): at most 75 encoded bytes for 74.
const uint8_t kMaxCobsLen = kMaxFrameLen + 1;

// Encode `len` bytes into `out` (room for len + len / 254 + 1 bytes); returns the encoded
// length, without the 0x00 delimiter. A run that ends exactly at the end of the input after a
// full 254-byte block gets no extra trailing block (as in Cheshire & Baker and the vectors).
uint16_t cobs_encode(const uint8_t* in, uint16_t len, uint8_t* out);

// Incremental decoder with a fixed buffer. Bytes between delimiters that decode to more than
// kMaxFrameLen bytes, or that are not valid COBS, are discarded up to the next 0x00.
class CobsDecoder {
 public:
  enum Result : uint8_t {
    kNone = 0,    // byte consumed, no frame ended
    kFrame = 1,   // a frame ended: data()/length() valid until the next feed()
    kError = 2,   // a frame ended but its COBS was invalid (truncated block): dropped
    kOverlong = 3,  // a frame ended that decodes to more than kMaxFrameLen bytes: dropped
  };

  CobsDecoder() { reset(); }
  void reset();
  Result feed(uint8_t byte);
  const uint8_t* data() const { return buf_; }
  uint8_t length() const { return len_; }

 private:
  uint8_t buf_[kMaxFrameLen];
  uint8_t len_;
  uint8_t remaining_;   // data bytes left in the current COBS block
  uint8_t code_;        // current block's code byte (0 = expecting the first code byte)
  bool overflow_;       // frame too long: discard until the delimiter
};

}  // namespace stipi

#endif

// frame.cpp -- protocol v1 frame codec (see frame.h and docs/protocol.md).
#include "frame.h"

#include "crc16.h"

namespace stipi {

uint8_t encode_frame(uint8_t* out, uint8_t type, uint16_t seq, uint32_t t_us, const uint8_t* body,
                     uint8_t body_len) {
  if (body_len > kMaxBodyLen) return 0;
  out[0] = kProtocolVersion;
  out[1] = type;
  put_u16(out + 2, seq);
  put_u32(out + 4, t_us);
  for (uint8_t i = 0; i < body_len; ++i) out[kHeaderLen + i] = body[i];
  const uint8_t n = static_cast<uint8_t>(kHeaderLen + body_len);
  put_u16(out + n, crc16(out, n));
  return static_cast<uint8_t>(n + kCrcLen);
}

uint8_t encode_samples(uint8_t* out, uint16_t seq, uint32_t t_us, uint32_t first_index,
                       uint16_t period_us, const uint16_t* adc, uint8_t count) {
  if (count == 0 || count > kMaxSamplesPerFrame) return 0;
  // Build the body in place after the header (encode_frame copies onto itself: same offsets).
  uint8_t* body = out + kHeaderLen;
  put_u32(body, first_index);
  put_u16(body + 4, period_us);
  body[6] = count;
  for (uint8_t i = 0; i < count; ++i) put_u16(body + 7 + 2 * i, adc[i]);
  return encode_frame(out, kMsgSamples, seq, t_us, body, static_cast<uint8_t>(7 + 2 * count));
}

uint8_t encode_status(uint8_t* out, uint16_t seq, uint32_t t_us, const StatusBody& s) {
  uint8_t* body = out + kHeaderLen;
  body[0] = s.led_level;
  put_u16(body + 1, s.rate_hz);
  put_u32(body + 3, s.dropped);
  put_u16(body + 7, s.supply_mv);
  body[9] = s.flags;
  body[10] = s.ble_state;
  put_u16(body + 11, s.ble_restarts);
  body[13] = s.reset_cause;
  return encode_frame(out, kMsgStatus, seq, t_us, body, 14);
}

uint8_t infer_reset_cause(uint8_t mcusr, bool ram_kept, bool watchdog_marked) {
  const uint8_t known = kResetPowerOn | kResetExternal | kResetBrownOut | kResetWatchdog;
  if (mcusr & known) return static_cast<uint8_t>(mcusr & known);  // no bootloader cleared it
  if (watchdog_marked && ram_kept) return kResetWatchdog;
  if (!ram_kept) return kResetPowerOn;  // RAM lost its contents: the power went
  // RAM kept, no watchdog mark: the reset pin or a brown-out; Caterina leaves the MCU in the
  // same state after both, so both bits say "one of these".
  return static_cast<uint8_t>(kResetExternal | kResetBrownOut);
}

uint8_t encode_ack(uint8_t* out, uint16_t seq, uint32_t t_us, uint16_t ref_seq, uint8_t cmd,
                   uint8_t status, const uint8_t* result, uint8_t result_len) {
  if (result_len > kMaxBodyLen - 4) return 0;
  uint8_t* body = out + kHeaderLen;
  put_u16(body, ref_seq);
  body[2] = cmd;
  body[3] = status;
  for (uint8_t i = 0; i < result_len; ++i) body[4 + i] = result[i];
  return encode_frame(out, kMsgAck, seq, t_us, body, static_cast<uint8_t>(4 + result_len));
}

uint8_t wire_encode(const uint8_t* frame, uint8_t len, uint8_t* out) {
  const uint8_t n = static_cast<uint8_t>(cobs_encode(frame, len, out));
  out[n] = 0;
  return static_cast<uint8_t>(n + 1);
}

DecodeResult check_frame(const uint8_t* frame, uint8_t len) {
  if (len < kMinFrameLen) return kDecodeTooShort;
  if (len > kMaxFrameLen) return kDecodeTooLong;
  const uint8_t n = static_cast<uint8_t>(len - kCrcLen);
  if (crc16(frame, n) != get_u16(frame + n)) return kDecodeBadCrc;
  if (frame[0] != kProtocolVersion) return kDecodeBadVersion;
  return kDecodeOk;
}

DecodeResult decode_command(const uint8_t* frame, uint8_t len, Command& out) {
  const DecodeResult r = check_frame(frame, len);
  if (r != kDecodeOk) return r;
  if (frame[1] != kMsgCommand) return kDecodeNotCommand;
  const uint8_t body_len = static_cast<uint8_t>(len - kCrcLen - kHeaderLen);
  if (body_len == 0) return kDecodeBadBody;
  out.seq = get_u16(frame + 2);
  out.t_us = get_u32(frame + 4);
  out.cmd = frame[kHeaderLen];
  out.arg_len = static_cast<uint8_t>(body_len - 1);
  for (uint8_t i = 0; i < out.arg_len && i < kMaxArgs; ++i) out.args[i] = frame[kHeaderLen + 1 + i];
  return kDecodeOk;
}

}  // namespace stipi

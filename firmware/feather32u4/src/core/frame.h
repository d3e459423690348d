// frame.h -- byte-exact codec for the STIP-I wire protocol v1 (docs/protocol.md).
//
// Owns: building SAMPLES, STATUS and ACK frames (header | body | crc16 LE), wrapping a frame for
// the wire (COBS + 0x00), and parsing a decoded COMMAND frame with its checks (length, CRC,
// version, type). Does not own sequence counters, links or what a command does (probe.h).
#ifndef STIPI_CORE_FRAME_H
#define STIPI_CORE_FRAME_H

#include <stdint.h>

#include "cobs.h"

namespace stipi {

const uint8_t kProtocolVersion = 1;
const uint8_t kHeaderLen = 8;
const uint8_t kCrcLen = 2;
const uint8_t kMinFrameLen = kHeaderLen + kCrcLen;  // 10
const uint8_t kMaxBodyLen = 64;
const uint8_t kMaxSamplesPerFrame = 24;
// A frame on the wire: COBS (<= 75 B) + delimiter.
const uint8_t kMaxWireLen = kMaxCobsLen + 1;

enum MsgType : uint8_t {
  kMsgSamples = 0x01,
  kMsgStatus = 0x02,
  kMsgCommand = 0x10,
  kMsgAck = 0x11,
};

enum CommandId : uint8_t {
  kCmdStreamStart = 0x01,
  kCmdStreamStop = 0x02,
  kCmdSetRate = 0x03,
  kCmdSetLed = 0x04,
  kCmdTare = 0x05,
  kCmdWriteCal = 0x06,
  kCmdGetInfo = 0x07,
};

enum AckStatus : uint8_t {
  kAckOk = 0,
  kAckUnknownCommand = 1,
  kAckBadArgument = 2,
  kAckBusy = 3,
  kAckEepromFailed = 4,
};

// STATUS.flags bits.
const uint8_t kFlagStreaming = 0x01;
const uint8_t kFlagBleConnected = 0x02;
const uint8_t kFlagUsbOpen = 0x04;
const uint8_t kFlagCalValid = 0x08;
const uint8_t kFlagSupplyUncorrected = 0x10;  // force not corrected for the FC22's 5 V supply

// STATUS.reset_cause bits, MCUSR's order (docs/protocol.md).
const uint8_t kResetPowerOn = 0x01;
const uint8_t kResetExternal = 0x02;
const uint8_t kResetBrownOut = 0x04;
const uint8_t kResetWatchdog = 0x08;

struct StatusBody {
  uint8_t led_level;
  uint16_t rate_hz;
  uint32_t dropped;
  uint16_t supply_mv;
  uint8_t flags;
  // The probe's health (firmware 1.1 on; a 14-byte body).
  uint8_t ble_state;      // 0 no BLE link, 1 absent, 2 booting, 3 up (BleHealth)
  uint16_t ble_restarts;  // times the module, once up, restarted and was probed again
  uint8_t reset_cause;    // kReset* bits
};

// Why the MCU started, from MCUSR as read at start-up (0 when a bootloader cleared it, as
// Caterina does), whether RAM kept a mark from the previous run (no power loss), and whether
// the watchdog interrupt marked an expiry just before the reset.
uint8_t infer_reset_cause(uint8_t mcusr, bool ram_kept, bool watchdog_marked);

// Little-endian helpers.
inline void put_u16(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v);
  p[1] = static_cast<uint8_t>(v >> 8);
}
inline void put_u32(uint8_t* p, uint32_t v) {
  put_u16(p, static_cast<uint16_t>(v));
  put_u16(p + 2, static_cast<uint16_t>(v >> 16));
}
inline uint16_t get_u16(const uint8_t* p) {
  return static_cast<uint16_t>(p[0] | (static_cast<uint16_t>(p[1]) << 8));
}
inline uint32_t get_u32(const uint8_t* p) {
  return static_cast<uint32_t>(get_u16(p)) | (static_cast<uint32_t>(get_u16(p + 2)) << 16);
}

// Build header | body | crc into `out` (room for kHeaderLen + body_len + kCrcLen bytes).
// Returns the frame length, or 0 if body_len > kMaxBodyLen.
uint8_t encode_frame(uint8_t* out, uint8_t type, uint16_t seq, uint32_t t_us, const uint8_t* body,
                     uint8_t body_len);

// SAMPLES: first_index u32, period_us u16, count u8 (1..24), count x adc u16.
// Returns the frame length, or 0 if count is 0 or above kMaxSamplesPerFrame.
uint8_t encode_samples(uint8_t* out, uint16_t seq, uint32_t t_us, uint32_t first_index,
                       uint16_t period_us, const uint16_t* adc, uint8_t count);

// STATUS: led_level u8, rate_hz u16, dropped u32, supply_mv u16, flags u8.
uint8_t encode_status(uint8_t* out, uint16_t seq, uint32_t t_us, const StatusBody& status);

// ACK: ref_seq u16, cmd u8, status u8, result (0..60 bytes). Returns 0 if result is too long.
uint8_t encode_ack(uint8_t* out, uint16_t seq, uint32_t t_us, uint16_t ref_seq, uint8_t cmd,
                   uint8_t status, const uint8_t* result, uint8_t result_len);

// COBS-encode a frame and append the 0x00 delimiter; `out` needs kMaxWireLen bytes.
uint8_t wire_encode(const uint8_t* frame, uint8_t len, uint8_t* out);

// Argument bytes kept from a COMMAND (the longest, WRITE_CAL, has 6); arg_len is the true
// length so that over-long arguments are still answered with "bad argument".
const uint8_t kMaxArgs = 8;

struct Command {
  uint16_t seq;
  uint32_t t_us;
  uint8_t cmd;
  uint8_t arg_len;     // argument bytes received (may exceed kMaxArgs)
  uint8_t args[kMaxArgs];
};

enum DecodeResult : uint8_t {
  kDecodeOk = 0,
  kDecodeTooShort = 1,   // fewer than 10 bytes
  kDecodeTooLong = 2,    // more than 74 bytes
  kDecodeBadCrc = 3,
  kDecodeBadVersion = 4, // counted and dropped (protocol)
  kDecodeNotCommand = 5, // a valid frame of another type: the probe only accepts COMMAND
  kDecodeBadBody = 6,    // a COMMAND without the cmd byte
};

// Checks shared by every frame type, in the protocol's order: decoded length, CRC, version.
DecodeResult check_frame(const uint8_t* frame, uint8_t len);

// Parse one decoded (un-COBSed) frame expected to be a COMMAND: check_frame, then type, then
// body (at least the cmd byte; argument lengths are judged by the command handler, which
// answers a wrong length with status 2).
DecodeResult decode_command(const uint8_t* frame, uint8_t len, Command& out);

}  // namespace stipi

#endif

// test_codec.cpp -- CRC-16, COBS and the frame codec against hand-made and protocol examples.
#include <cstring>
#include <random>
#include <vector>

#include "../src/core/cobs.h"
#include "../src/core/crc16.h"
#include "../src/core/frame.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

TEST(crc16_check_value_is_0x29B1) {
  const char* s = "123456789";
  CHECK_EQ(crc16(reinterpret_cast<const uint8_t*>(s), 9), 0x29B1);
  CHECK_EQ(crc16(nullptr, 0), 0xFFFF);
}

TEST(crc16_update_is_incremental) {
  const uint8_t d[] = {1, 2, 3, 4, 5, 6};
  CHECK_EQ(crc16_update(crc16(d, 2), d + 2, 4), crc16(d, 6));
}

static std::vector<uint8_t> enc(const std::vector<uint8_t>& in) {
  std::vector<uint8_t> out(in.size() + in.size() / 254 + 2);
  out.resize(cobs_encode(in.data(), static_cast<uint16_t>(in.size()), out.data()));
  return out;
}

TEST(cobs_encodes_the_published_examples) {
  CHECK(enc({0x00}) == (std::vector<uint8_t>{0x01, 0x01}));
  CHECK(enc({0x00, 0x00}) == (std::vector<uint8_t>{0x01, 0x01, 0x01}));
  CHECK(enc({0x11, 0x22, 0x00, 0x33}) == (std::vector<uint8_t>{0x03, 0x11, 0x22, 0x02, 0x33}));
  CHECK(enc({0x11, 0x22, 0x33, 0x44}) == (std::vector<uint8_t>{0x05, 0x11, 0x22, 0x33, 0x44}));
  CHECK(enc({0x11, 0x00, 0x00, 0x00}) == (std::vector<uint8_t>{0x02, 0x11, 0x01, 0x01, 0x01}));
  CHECK(enc({}) == (std::vector<uint8_t>{0x01}));
}

static std::vector<std::vector<uint8_t>> feed_all(CobsDecoder& d, const std::vector<uint8_t>& bytes,
                                                  int* errors) {
  std::vector<std::vector<uint8_t>> frames;
  for (uint8_t b : bytes) {
    const CobsDecoder::Result r = d.feed(b);
    if (r == CobsDecoder::kFrame) frames.emplace_back(d.data(), d.data() + d.length());
    if (r == CobsDecoder::kError || r == CobsDecoder::kOverlong) ++*errors;
  }
  return frames;
}

TEST(cobs_round_trip_random_frames_split_anywhere) {
  std::mt19937 rng(1234);
  for (int trial = 0; trial < 500; ++trial) {
    std::vector<uint8_t> frame(rng() % (kMaxFrameLen + 1));
    for (auto& b : frame) b = static_cast<uint8_t>(rng() % 4 == 0 ? 0 : rng());
    if (frame.empty()) frame.push_back(7);
    std::vector<uint8_t> wire = enc(frame);
    for (uint8_t b : wire) CHECK(b != 0);
    wire.push_back(0);
    CobsDecoder d;
    int errors = 0;
    // feed in two arbitrary pieces (a BLE notification boundary)
    const size_t cut = rng() % wire.size();
    auto f1 = feed_all(d, std::vector<uint8_t>(wire.begin(), wire.begin() + cut), &errors);
    auto f2 = feed_all(d, std::vector<uint8_t>(wire.begin() + cut, wire.end()), &errors);
    CHECK(f1.empty());
    CHECK_EQ(f2.size(), 1u);
    CHECK_EQ(errors, 0);
    if (f2.size() == 1) CHECK(f2[0] == frame);
  }
}

TEST(cobs_decoder_resyncs_after_garbage_and_ignores_empty_frames) {
  CobsDecoder d;
  int errors = 0;
  std::vector<uint8_t> bytes = {0x05, 0x11, 0x22};  // truncated frame (started mid-stream)
  bytes.push_back(0);
  bytes.push_back(0);  // empty frame
  const std::vector<uint8_t> good = {0x03, 0x11, 0x22, 0x02, 0x33, 0x00};
  bytes.insert(bytes.end(), good.begin(), good.end());
  auto frames = feed_all(d, bytes, &errors);
  CHECK_EQ(errors, 1);
  CHECK_EQ(frames.size(), 1u);
  if (!frames.empty()) CHECK(frames[0] == (std::vector<uint8_t>{0x11, 0x22, 0x00, 0x33}));
}

TEST(cobs_decoder_discards_overlong_frames_without_buffering) {
  CobsDecoder d;
  int errors = 0;
  std::vector<uint8_t> bytes(1, 0xFF);
  for (int i = 0; i < 200; ++i) bytes.push_back(0x42);  // far beyond 74 decoded bytes
  bytes.push_back(0);
  const std::vector<uint8_t> good = {0x02, 0x01, 0x00};
  bytes.insert(bytes.end(), good.begin(), good.end());
  auto frames = feed_all(d, bytes, &errors);
  CHECK_EQ(errors, 1);
  CHECK_EQ(frames.size(), 1u);
  if (!frames.empty()) CHECK(frames[0] == (std::vector<uint8_t>{0x01}));
}

TEST(samples_frame_layout_matches_protocol_doc) {
  const uint16_t adc[10] = {0, 1, 2, 3, 1023, 512, 7, 8, 9, 10};
  uint8_t f[kMaxFrameLen];
  const uint8_t n = encode_samples(f, 0x1234, 0xA1B2C3D4, 0x01020304, 10000, adc, 10);
  CHECK_EQ(n, 17 + 2 * 10);  // protocol.md: 17 + 2n bytes
  CHECK_EQ(f[0], 1);
  CHECK_EQ(f[1], kMsgSamples);
  CHECK_EQ(get_u16(f + 2), 0x1234);
  CHECK_EQ(get_u32(f + 4), 0xA1B2C3D4u);
  CHECK_EQ(get_u32(f + 8), 0x01020304u);
  CHECK_EQ(get_u16(f + 12), 10000);
  CHECK_EQ(f[14], 10);
  CHECK_EQ(get_u16(f + 15 + 2 * 4), 1023);
  CHECK_EQ(get_u16(f + n - 2), crc16(f, static_cast<uint16_t>(n - 2)));
  uint8_t w[kMaxWireLen];
  CHECK_EQ(wire_encode(f, n, w), 19 + 2 * 10);  // 39 B on the wire for n = 10
  CHECK_EQ(w[38], 0);
  CHECK_EQ(encode_samples(f, 0, 0, 0, 1, adc, 0), 0);
  uint16_t many[25] = {};
  CHECK_EQ(encode_samples(f, 0, 0, 0, 1, many, 25), 0);
  CHECK_EQ(encode_samples(f, 0, 0, 0, 1, many, 24), 17 + 48);
}

TEST(status_and_ack_layouts) {
  StatusBody s;
  s.led_level = 200;
  s.rate_hz = 1000;
  s.dropped = 0x11223344;
  s.supply_mv = 4100;
  s.flags = kFlagStreaming | kFlagCalValid;
  s.ble_state = 2;
  s.ble_restarts = 0x0102;
  s.reset_cause = kResetExternal | kResetBrownOut;
  uint8_t f[kMaxFrameLen];
  CHECK_EQ(encode_status(f, 7, 99, s), 24);
  CHECK_EQ(f[1], kMsgStatus);
  CHECK_EQ(f[8], 200);
  CHECK_EQ(get_u16(f + 9), 1000);
  CHECK_EQ(get_u32(f + 11), 0x11223344u);
  CHECK_EQ(get_u16(f + 15), 4100);
  CHECK_EQ(f[17], 0x09);
  CHECK_EQ(f[18], 2);
  CHECK_EQ(get_u16(f + 19), 0x0102);
  CHECK_EQ(f[21], 0x06);
  const uint8_t r[2] = {0x34, 0x02};
  CHECK_EQ(encode_ack(f, 8, 5, 0xBEEF, kCmdTare, kAckOk, r, 2), 16);
  CHECK_EQ(f[1], kMsgAck);
  CHECK_EQ(get_u16(f + 8), 0xBEEF);
  CHECK_EQ(f[10], kCmdTare);
  CHECK_EQ(f[11], kAckOk);
  CHECK_EQ(get_u16(f + 12), 0x0234);
}

TEST(decode_command_checks_crc_version_type_and_length) {
  uint8_t f[kMaxFrameLen];
  const uint8_t args[3] = {kCmdSetRate, 0xE8, 0x03};
  uint8_t n = encode_frame(f, kMsgCommand, 42, 1000, args, 3);
  Command c;
  CHECK_EQ(decode_command(f, n, c), kDecodeOk);
  CHECK_EQ(c.seq, 42);
  CHECK_EQ(c.t_us, 1000u);
  CHECK_EQ(c.cmd, kCmdSetRate);
  CHECK_EQ(c.arg_len, 2);
  CHECK_EQ(get_u16(c.args), 1000);
  f[9] ^= 1;
  CHECK_EQ(decode_command(f, n, c), kDecodeBadCrc);
  f[9] ^= 1;
  CHECK_EQ(decode_command(f, 9, c), kDecodeTooShort);
  CHECK_EQ(decode_command(f, 75, c), kDecodeTooLong);
  n = encode_frame(f, kMsgAck, 1, 0, args, 3);
  CHECK_EQ(decode_command(f, n, c), kDecodeNotCommand);
  n = encode_frame(f, kMsgCommand, 1, 0, args, 3);
  f[0] = 2;
  put_u16(f + n - 2, crc16(f, static_cast<uint16_t>(n - 2)));
  CHECK_EQ(decode_command(f, n, c), kDecodeBadVersion);
  n = encode_frame(f, kMsgCommand, 1, 0, args, 0);
  CHECK_EQ(decode_command(f, n, c), kDecodeBadBody);  // no cmd byte: rejected, not answered
  uint8_t big[30] = {kCmdWriteCal};
  n = encode_frame(f, kMsgCommand, 1, 0, big, 30);
  CHECK_EQ(decode_command(f, n, c), kDecodeOk);
  CHECK_EQ(c.arg_len, 29);  // true length kept, storage bounded
}

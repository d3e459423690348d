// test_probe.cpp -- the probe's command handler, streaming, TARE and heartbeat, driven through
// real frames on fake links with a fake timer/ADC and clock.
#include <vector>

#include "../src/core/cal_store.h"
#include "../src/core/frame.h"
#include "../src/core/probe.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;
using fakes::HostFrame;

namespace {

struct Rig {
  explicit Rig(uint32_t start_us = 1000) : clock(start_us), board(clock, sampler),
                                           probe(clock, board, sampler, eeprom) {}
  void begin() {
    probe.set_link(kLinkUsb, &usb);
    probe.set_link(kLinkUart, &uart);
    probe.set_link(kLinkBle, &ble);
    probe.begin();
  }
  // Let time pass in 1 ms steps, running the main loop after each.
  void run(uint32_t us, uint32_t step = 1000) {
    for (uint32_t t = 0; t < us; t += step) {
      board.advance(step);
      probe.poll();
    }
  }
  std::vector<HostFrame> frames(fakes::FakeLink& link) { return fakes::take_frames(link.tx); }
  std::vector<HostFrame> frames() { return frames(uart); }
  // Send a command on `link`, run one loop pass, return every frame the UART got since.
  std::vector<HostFrame> command(uint16_t seq, uint8_t cmd, const std::vector<uint8_t>& args = {},
                                 fakes::FakeLink* link = nullptr) {
    (link ? link : &uart)->push(fakes::command_wire(seq, cmd, args));
    probe.poll();
    return frames();
  }

  fakes::FakeClock clock;
  Sampler sampler;
  fakes::FakeBoard board;
  fakes::FakeEeprom eeprom;
  fakes::FakeLink usb, uart, ble;
  Probe probe;
};

const HostFrame* find_ack(const std::vector<HostFrame>& fs, uint16_t ref_seq) {
  for (const HostFrame& f : fs) {
    if (f.type == kMsgAck && get_u16(f.body.data()) == ref_seq) return &f;
  }
  return nullptr;
}

int ack_status(const std::vector<HostFrame>& fs, uint16_t ref_seq, uint8_t cmd) {
  const HostFrame* a = find_ack(fs, ref_seq);
  if (!a) return -1;
  CHECK_EQ(a->body[2], cmd);
  return a->body[3];
}

std::vector<HostFrame> of_type(const std::vector<HostFrame>& fs, uint8_t type) {
  std::vector<HostFrame> out;
  for (const HostFrame& f : fs) {
    if (f.type == type) out.push_back(f);
  }
  return out;
}

std::vector<uint8_t> le16(uint16_t v) { return {static_cast<uint8_t>(v), static_cast<uint8_t>(v >> 8)}; }

}  // namespace

TEST(probe_boot_flushes_receivers_and_sends_status_every_500ms) {
  Rig r;
  r.usb.open = false;
  r.ble.open = false;
  r.probe.set_reset_cause(kResetWatchdog);
  r.begin();
  CHECK(r.uart.tx == std::vector<uint8_t>{0});  // leading 0x00 flushes a partial frame
  CHECK(r.usb.tx.empty());                      // closed links get nothing
  r.run(5000000);
  const auto fs = r.frames();
  CHECK_EQ(fs.size(), 10u);  // first loop pass, then every 0.5 s
  uint16_t seq = 0;
  uint32_t last_t = 0;
  for (const HostFrame& f : fs) {
    CHECK(f.crc_ok);
    CHECK_EQ(f.version, 1);
    CHECK_EQ(f.type, kMsgStatus);
    CHECK_EQ(f.seq, seq++);
    CHECK_EQ(f.body.size(), 14u);
    CHECK_EQ(f.body[0], 0);                                   // LED off
    CHECK_EQ(get_u16(f.body.data() + 1), STIPI_DEFAULT_RATE_HZ);
    CHECK_EQ(get_u32(f.body.data() + 3), 0u);                 // dropped
    CHECK_EQ(get_u16(f.body.data() + 7), 4123);               // supply_mv from the board
    CHECK_EQ(f.body[9], 0);                                   // no flags
    CHECK_EQ(f.body[10], 0);                                  // no BLE health given
    CHECK_EQ(get_u16(f.body.data() + 11), 0u);                // no module restarts
    CHECK_EQ(f.body[13], kResetWatchdog);                     // the reset cause given
    if (seq > 1) CHECK(f.t_us - last_t <= 1000000u);
    last_t = f.t_us;
  }
  CHECK_EQ(r.board.supply_requests, 10);
}

TEST(probe_sends_identical_frames_to_every_open_link) {
  Rig r;
  r.begin();
  r.run(100000);
  r.uart.push(fakes::command_wire(1, kCmdStreamStart, {}));
  r.run(300000);
  CHECK(!r.uart.tx.empty());
  CHECK(r.uart.tx == r.usb.tx);
  CHECK(r.uart.tx == r.ble.tx);
  const auto fs = r.frames(r.usb);
  CHECK(fs[0].body[9] & kFlagUsbOpen);
  CHECK(fs[0].body[9] & kFlagBleConnected);
}

TEST(probe_streams_consecutive_batches_with_sample_timestamps) {
  Rig r;
  r.begin();
  r.run(10000);
  r.frames();
  auto fs = r.command(5, kCmdStreamStart);
  CHECK_EQ(ack_status(fs, 5, kCmdStreamStart), kAckOk);
  CHECK(r.board.sampling);
  CHECK_EQ(r.board.period, 10000);
  const uint32_t first_sample_us = r.board.next_us;
  r.run(1000000);
  fs = r.frames();
  const auto samples = of_type(fs, kMsgSamples);
  CHECK_EQ(samples.size(), 10u);  // 100 Hz, 10 per batch, 1 s
  uint32_t expect_index = 0;
  for (const HostFrame& f : samples) {
    const uint8_t* b = f.body.data();
    CHECK_EQ(get_u32(b), expect_index);
    CHECK_EQ(get_u16(b + 4), 10000);
    CHECK_EQ(b[6], STIPI_BATCH_SIZE);
    CHECK_EQ(f.body.size(), 7u + 2 * STIPI_BATCH_SIZE);
    CHECK_EQ(f.t_us, first_sample_us + expect_index * 10000);
    for (uint8_t i = 0; i < b[6]; ++i) CHECK_EQ(get_u16(b + 7 + 2 * i), (expect_index + i) & 0x3FF);
    expect_index += b[6];
  }
  const auto status = of_type(fs, kMsgStatus);
  CHECK(!status.empty());
  CHECK(status.back().body[9] & kFlagStreaming);
  fs = r.command(6, kCmdStreamStart);  // idempotent
  CHECK_EQ(ack_status(fs, 6, kCmdStreamStart), kAckOk);
  CHECK_EQ(r.board.starts, 1);
}

TEST(probe_stream_stop_flushes_partial_batch_before_ack) {
  Rig r;
  r.begin();
  r.command(1, kCmdStreamStart);
  r.run(125000);  // 12 samples: one batch sent, 2 queued
  r.frames();
  auto fs = r.command(2, kCmdStreamStop);
  CHECK(!r.board.sampling);
  CHECK_EQ(fs.size(), 2u);
  CHECK_EQ(fs[0].type, kMsgSamples);
  CHECK_EQ(get_u32(fs[0].body.data()), 10u);
  CHECK_EQ(fs[0].body[6], 2);
  CHECK_EQ(fs[1].type, kMsgAck);
  CHECK_EQ(fs[1].body[3], kAckOk);
  r.run(1000000);
  CHECK(of_type(r.frames(), kMsgSamples).empty());
  // restart: indices continue where they stopped
  r.command(3, kCmdStreamStart);
  r.run(100000);
  const auto s = of_type(r.frames(), kMsgSamples);
  CHECK_EQ(s.size(), 1u);
  if (!s.empty()) CHECK_EQ(get_u32(s[0].body.data()), 12u);
}

TEST(probe_set_rate_validates_and_applies_between_batches) {
  Rig r;
  r.begin();
  for (int bad : {0, 1, 15, 1001, 65535}) {
    auto fs = r.command(10, kCmdSetRate, le16(static_cast<uint16_t>(bad)));
    CHECK_EQ(ack_status(fs, 10, kCmdSetRate), kAckBadArgument);
  }
  auto fs = r.command(11, kCmdSetRate, {0xE8});
  CHECK_EQ(ack_status(fs, 11, kCmdSetRate), kAckBadArgument);
  fs = r.command(12, kCmdSetRate, {0xE8, 0x03, 0x00});
  CHECK_EQ(ack_status(fs, 12, kCmdSetRate), kAckBadArgument);
  CHECK_EQ(r.probe.rate_hz(), STIPI_DEFAULT_RATE_HZ);
  fs = r.command(13, kCmdSetRate, le16(16));
  CHECK_EQ(ack_status(fs, 13, kCmdSetRate), kAckOk);
  CHECK_EQ(r.probe.rate_hz(), 16);
  r.command(14, kCmdStreamStart);
  CHECK_EQ(r.board.period, 62500);
  r.run(200000);  // 3 samples at 16 Hz
  r.frames();
  fs = r.command(15, kCmdSetRate, le16(1000));
  CHECK_EQ(ack_status(fs, 15, kCmdSetRate), kAckOk);
  auto s = of_type(fs, kMsgSamples);
  CHECK_EQ(s.size(), 1u);  // the old-rate samples leave first, with their own period
  if (!s.empty()) {
    CHECK_EQ(get_u16(s[0].body.data() + 4), 62500);
    CHECK_EQ(s[0].body[6], 3);
  }
  CHECK_EQ(r.board.period, 1000);
  r.run(100000);
  s = of_type(r.frames(), kMsgSamples);
  CHECK_EQ(s.size(), 10u);
  if (!s.empty()) {
    CHECK_EQ(get_u16(s[0].body.data() + 4), 1000);
    CHECK_EQ(get_u32(s[0].body.data()), 3u);
  }
  fs = r.command(16, kCmdSetRate, le16(300));
  CHECK_EQ(r.board.period, 3333);  // rounded to the nearest microsecond
}

TEST(probe_set_led_and_unknown_and_empty_commands) {
  Rig r;
  r.begin();
  auto fs = r.command(1, kCmdSetLed, {200});
  CHECK_EQ(ack_status(fs, 1, kCmdSetLed), kAckOk);
  CHECK_EQ(r.board.led, 200);
  fs = r.command(2, kCmdSetLed, {});
  CHECK_EQ(ack_status(fs, 2, kCmdSetLed), kAckBadArgument);
  fs = r.command(3, kCmdSetLed, {1, 2});
  CHECK_EQ(ack_status(fs, 3, kCmdSetLed), kAckBadArgument);
  CHECK_EQ(r.board.led, 200);
  fs = r.command(4, 0x42);
  CHECK_EQ(ack_status(fs, 4, 0x42), kAckUnknownCommand);
  fs = r.command(5, 0x00);
  CHECK_EQ(ack_status(fs, 5, 0x00), kAckUnknownCommand);
  for (uint8_t cmd : {kCmdStreamStart, kCmdStreamStop, kCmdTare, kCmdGetInfo}) {
    fs = r.command(6, cmd, {0});
    CHECK_EQ(ack_status(fs, 6, cmd), kAckBadArgument);
  }
  // COMMAND with an empty body: not a command (vector invalid_command_empty_body): no ACK
  uint8_t f[kMaxFrameLen];
  uint8_t w[kMaxWireLen];
  const uint8_t n = encode_frame(f, kMsgCommand, 7, 0, nullptr, 0);
  const uint8_t wn = wire_encode(f, n, w);
  const uint32_t errors = r.probe.rx_errors();
  r.uart.push(std::vector<uint8_t>(w, w + wn));
  r.probe.poll();
  fs = r.frames();
  CHECK(find_ack(fs, 7) == nullptr);
  CHECK_EQ(r.probe.rx_errors(), errors + 1);
  // STATUS reports the LED level
  r.run(600000);
  const auto st = of_type(r.frames(), kMsgStatus);
  CHECK(!st.empty());
  if (!st.empty()) CHECK_EQ(st.back().body[0], 200);
}

TEST(probe_get_info_layout) {
  Rig r;
  r.begin();
  r.command(1, kCmdSetLed, {77});
  r.command(2, kCmdWriteCal, {0x10, 0x02, 0x40, 0xE2, 0x01, 0x00});  // 528, 123456
  auto fs = r.command(3, kCmdGetInfo);
  const HostFrame* a = find_ack(fs, 3);
  CHECK(a != nullptr);
  if (!a) return;
  const std::vector<uint8_t>& b = a->body;
  CHECK_EQ(b.size(), 4u + 15u);
  CHECK_EQ(b[3], kAckOk);
  CHECK_EQ(b[4], 1);  // proto
  CHECK_EQ(b[5], STIPI_FW_MAJOR);
  CHECK_EQ(b[6], STIPI_FW_MINOR);
  CHECK_EQ(b[7], STIPI_FW_PATCH);
  CHECK_EQ(get_u16(b.data() + 8), STIPI_DEFAULT_RATE_HZ);
  CHECK_EQ(b[10], 77);
  CHECK_EQ(get_u16(b.data() + 11), 528);
  CHECK_EQ(static_cast<int32_t>(get_u32(b.data() + 13)), 123456);
  CHECK_EQ(b[17], 10);
  CHECK_EQ(b[18], STIPI_BATCH_SIZE);
}

TEST(probe_write_cal_validates_persists_and_sets_flag) {
  Rig r;
  r.begin();
  auto fs = r.command(1, kCmdWriteCal, {0x00, 0x04, 1, 0, 0, 0});  // zero 1024 > 10 bit
  CHECK_EQ(ack_status(fs, 1, kCmdWriteCal), kAckBadArgument);
  fs = r.command(2, kCmdWriteCal, {0x10, 0x00, 0, 0, 0, 0});  // span 0
  CHECK_EQ(ack_status(fs, 2, kCmdWriteCal), kAckBadArgument);
  fs = r.command(3, kCmdWriteCal, {0x10, 0x00, 0, 0, 0});  // 5 bytes
  CHECK_EQ(ack_status(fs, 3, kCmdWriteCal), kAckBadArgument);
  CHECK(!r.probe.cal_valid());
  fs = r.command(4, kCmdWriteCal, {0xFF, 0x03, 0xFF, 0xFF, 0xFF, 0xFF});  // 1023, -1
  CHECK_EQ(ack_status(fs, 4, kCmdWriteCal), kAckOk);
  CHECK(r.probe.cal_valid());
  CHECK_EQ(r.probe.calibration().span_un_per_count, -1);
  r.eeprom.stuck = true;
  fs = r.command(5, kCmdWriteCal, {0x01, 0x00, 0x05, 0, 0, 0});
  CHECK_EQ(ack_status(fs, 5, kCmdWriteCal), kAckEepromFailed);
  CHECK_EQ(r.probe.calibration().zero_counts, 1023);  // RAM keeps what EEPROM holds
  // a reboot loads the stored calibration and reports it valid
  Rig r2;
  r2.eeprom.mem = r.eeprom.mem;
  r2.begin();
  CHECK(r2.probe.cal_valid());
  CHECK_EQ(r2.probe.calibration().zero_counts, 1023);
  r2.run(1000);
  const auto st = of_type(r2.frames(), kMsgStatus);
  CHECK(!st.empty());
  if (!st.empty()) CHECK(st[0].body[9] & kFlagCalValid);
}

TEST(probe_tare_when_idle_averages_16_samples_and_stops) {
  Rig r;
  r.begin();
  r.board.adc = [](uint32_t i) { return static_cast<uint16_t>(500 + (i % 4)); };  // mean 501.5
  auto fs = r.command(9, kCmdTare);
  CHECK(find_ack(fs, 9) == nullptr);  // answered when the samples are in
  CHECK(r.board.sampling);
  CHECK(r.probe.tare_pending());
  r.run(150000);  // 15 samples at 100 Hz
  CHECK(find_ack(r.frames(), 9) == nullptr);
  r.run(20000);
  fs = r.frames();
  const HostFrame* a = find_ack(fs, 9);
  CHECK(a != nullptr);
  if (a) {
    CHECK_EQ(a->body[2], kCmdTare);
    CHECK_EQ(a->body[3], kAckOk);
    CHECK_EQ(get_u16(a->body.data() + 4), 502);  // round(501.5)
  }
  CHECK(!r.board.sampling);
  CHECK(of_type(fs, kMsgSamples).empty());  // tare samples are not streamed
  CHECK_EQ(r.probe.calibration().zero_counts, 502);
  CHECK(!r.probe.cal_valid());  // zero without a span is not a calibration
  CalStore store(r.eeprom, STIPI_EEPROM_CAL_ADDR);
  Calibration c = {};
  CHECK(store.load(c));
  CHECK_EQ(c.zero_counts, 502);
}

TEST(probe_tare_while_streaming_uses_only_later_samples_and_blocks_rate_changes) {
  Rig r;
  r.begin();
  r.command(1, kCmdWriteCal, {0, 0, 100, 0, 0, 0});
  r.board.adc = [](uint32_t i) { return static_cast<uint16_t>(i < 15 ? 900 : 300); };
  r.command(2, kCmdStreamStart);
  r.run(150000);  // samples 0..14 taken (value 900), 10 sent, 5 queued
  r.frames();
  auto fs = r.command(3, kCmdTare);
  CHECK(find_ack(fs, 3) == nullptr);
  for (uint8_t cmd : {kCmdStreamStop, kCmdTare}) {
    fs = r.command(4, cmd);
    CHECK_EQ(ack_status(fs, 4, cmd), kAckBusy);
  }
  fs = r.command(5, kCmdSetRate, le16(200));
  CHECK_EQ(ack_status(fs, 5, kCmdSetRate), kAckBusy);
  fs = r.command(6, kCmdWriteCal, {0, 0, 1, 0, 0, 0});
  CHECK_EQ(ack_status(fs, 6, kCmdWriteCal), kAckBusy);
  fs = r.command(7, kCmdSetLed, {3});
  CHECK_EQ(ack_status(fs, 7, kCmdSetLed), kAckOk);
  fs = r.command(8, kCmdGetInfo);
  CHECK_EQ(ack_status(fs, 8, kCmdGetInfo), kAckOk);
  r.run(300000);
  fs = r.frames();
  const HostFrame* a = find_ack(fs, 3);
  CHECK(a != nullptr);
  if (a) CHECK_EQ(get_u16(a->body.data() + 4), 300);  // none of the 900s taken before TARE
  CHECK(r.board.sampling);                           // streaming continues
  CHECK(r.probe.cal_valid());                        // span 100 kept
  CHECK_EQ(r.probe.calibration().span_un_per_count, 100);
  uint32_t expect = 10;
  for (const HostFrame& f : of_type(fs, kMsgSamples)) {
    CHECK_EQ(get_u32(f.body.data()), expect);
    expect += f.body[6];
  }
  fs = r.command(9, kCmdStreamStop);
  CHECK_EQ(ack_status(fs, 9, kCmdStreamStop), kAckOk);
}

TEST(probe_tare_reports_eeprom_failure) {
  Rig r;
  r.begin();
  r.eeprom.stuck = true;
  r.command(1, kCmdTare);
  r.run(200000);
  CHECK_EQ(ack_status(r.frames(), 1, kCmdTare), kAckEepromFailed);
  CHECK_EQ(r.probe.calibration().zero_counts, 0);
}

TEST(probe_rejects_corrupt_frames_and_reassembles_split_commands) {
  Rig r;
  r.begin();
  r.run(1000);
  r.frames();
  uint8_t f[kMaxFrameLen];
  uint8_t wire[kMaxWireLen];
  const uint8_t arg[2] = {kCmdSetLed, 9};
  const uint8_t n = encode_frame(f, kMsgCommand, 1, 0, arg, 2);
  f[9] = 8;  // corrupt the argument after the CRC was computed
  const uint8_t wn = wire_encode(f, n, wire);
  r.uart.push(std::vector<uint8_t>(wire, wire + wn));
  std::vector<uint8_t> w;
  r.probe.poll();
  CHECK(find_ack(r.frames(), 1) == nullptr);
  CHECK_EQ(r.probe.rx_errors(), 1u);
  // wrong protocol version: counted and dropped
  // a command arriving one byte per loop pass, on the BLE link; ACK goes to every link
  w = fakes::command_wire(2, kCmdSetLed, {9});
  for (uint8_t b : w) {
    r.ble.push({b});
    r.probe.poll();
  }
  CHECK_EQ(ack_status(r.frames(), 2, kCmdSetLed), kAckOk);
  CHECK_EQ(ack_status(r.frames(r.ble), 2, kCmdSetLed), kAckOk);
  // garbage without delimiter, then a good command: resync at the 0x00
  r.usb.push({0x11, 0x22, 0x33, 0x00});
  r.usb.push(fakes::command_wire(3, kCmdSetLed, {10}));
  for (int i = 0; i < 3; ++i) r.probe.poll();
  CHECK_EQ(ack_status(r.frames(), 3, kCmdSetLed), kAckOk);
  CHECK_EQ(r.board.led, 10);
}

TEST(probe_link_that_cannot_take_a_frame_sees_a_seq_gap) {
  Rig r;
  r.begin();
  r.run(1000);
  r.ble.accept = false;
  r.uart.push(fakes::command_wire(1, kCmdSetLed, {1}));
  r.probe.poll();
  r.ble.accept = true;
  r.uart.push(fakes::command_wire(2, kCmdSetLed, {2}));
  r.probe.poll();
  const auto ble = r.frames(r.ble);
  const auto uart = r.frames(r.uart);
  CHECK_EQ(r.probe.link_drops(kLinkBle), 1u);
  CHECK_EQ(uart.size(), ble.size() + 1);
  CHECK_EQ(static_cast<uint16_t>(ble.back().seq - ble[ble.size() - 2].seq), 2);
}

TEST(probe_overflow_is_reported_in_status_and_first_index_gap) {
  Rig r;
  r.begin();
  r.command(1, kCmdSetRate, le16(1000));
  r.command(2, kCmdStreamStart);
  r.run(20000);
  r.board.advance(200000);  // main loop stalled 200 ms: 200 samples into a 128-sample ring
  r.run(400000);
  const auto fs = r.frames();
  uint32_t expect = 0, gaps = 0;
  for (const HostFrame& f : of_type(fs, kMsgSamples)) {
    const uint32_t first = get_u32(f.body.data());
    gaps += first - expect;
    expect = first + f.body[6];
  }
  const uint32_t dropped = r.sampler.dropped();
  CHECK(dropped > 0);
  CHECK_EQ(gaps, dropped);  // every lost sample accounted for
  r.run(600000);
  const auto st = of_type(r.frames(), kMsgStatus);
  CHECK(!st.empty());
  if (!st.empty()) CHECK_EQ(get_u32(st.back().body.data() + 3), dropped);
}

TEST(probe_timestamps_continue_across_micros_wrap) {
  Rig r(0xFFFFFFFFu - 300000);  // 0.3 s before micros() wraps
  r.begin();
  r.command(1, kCmdStreamStart);
  r.run(1000000);
  const auto s = of_type(r.frames(), kMsgSamples);
  CHECK_EQ(s.size(), 10u);
  for (size_t i = 1; i < s.size(); ++i) {
    CHECK_EQ(static_cast<uint32_t>(s[i].t_us - s[i - 1].t_us), 100000u);
  }
  CHECK(s.front().t_us > 0x80000000u);
  CHECK(s.back().t_us < 0x80000000u);  // wrapped
}

TEST(probe_flags_force_not_supply_corrected) {
  Rig r;
  r.usb.open = false;
  r.ble.open = false;
  r.board.corrected = false;  // no 5 V sense wired (config.h STIPI_PIN_SUPPLY5 = -1)
  r.begin();
  r.run(600000);
  const auto fs = r.frames();
  CHECK(fs.size() >= 2u);
  for (const HostFrame& f : fs) CHECK_EQ(f.body[9], kFlagSupplyUncorrected);
  r.board.corrected = true;  // a plausible 5 V reading arrived
  r.run(600000);
  CHECK_EQ(r.frames().back().body[9], 0);
}

TEST(reset_cause_from_mcusr_or_inferred_after_caterina_cleared_it) {
  // MCUSR kept (no bootloader, or one that passes it on): its bits as they are.
  CHECK_EQ(infer_reset_cause(0x01, false, false), kResetPowerOn);
  CHECK_EQ(infer_reset_cause(0x08, true, false), kResetWatchdog);
  CHECK_EQ(infer_reset_cause(0x04, true, true), kResetBrownOut);
  CHECK_EQ(infer_reset_cause(0x02 | 0x80, true, false), kResetExternal);  // JTRF etc. dropped
  // Caterina cleared MCUSR (a Feather): inferred from RAM and the watchdog interrupt's mark.
  CHECK_EQ(infer_reset_cause(0, false, false), kResetPowerOn);
  CHECK_EQ(infer_reset_cause(0, false, true), kResetPowerOn);  // a mark in lost RAM is noise
  CHECK_EQ(infer_reset_cause(0, true, true), kResetWatchdog);
  CHECK_EQ(infer_reset_cause(0, true, false), kResetExternal | kResetBrownOut);
}

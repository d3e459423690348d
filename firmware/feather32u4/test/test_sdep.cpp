// test_sdep.cpp -- SDEP driver and BLE UART link against a fake nRF51822 SPI responder.
#include <string>
#include <vector>

#include "../src/core/probe.h"
#include "../src/core/sdep.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

namespace {
std::vector<uint8_t> bytes(const std::string& s) { return std::vector<uint8_t>(s.begin(), s.end()); }

// Run the link's life cycle until it settles (ready or absent), in 1 ms steps.
void settle(BleUartLink& link, fakes::FakeClock& clock) {
  for (int i = 0; i < 5000 && link.state() != BleUartLink::kReady &&
                  link.state() != BleUartLink::kAbsent; ++i) {
    clock.now_us += 1000;
    link.poll();
  }
}
}  // namespace

TEST(sdep_send_packet_header_and_cs_setup_time) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  const std::vector<uint8_t> p = bytes("ATI");
  CHECK_EQ(d.send_packet(kSdepCommand, kSdepCmdAtWrapper, p.data(), 3, false), kSdepOk);
  CHECK_EQ(nrf.cs_too_early, 0);
  CHECK_EQ(nrf.commands.size(), 1u);
  CHECK_EQ(nrf.commands[0].type, 0x10);
  CHECK_EQ(nrf.commands[0].id, 0x0A00);
  CHECK(!nrf.commands[0].more);
  CHECK(nrf.commands[0].payload == p);
  CHECK_EQ(d.send_packet(kSdepCommand, 1, p.data(), 17, false), kSdepBadPacket);
}

TEST(sdep_long_command_is_split_with_more_data_bits) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  const std::string cmd = "AT+GAPDEVNAME=STIPI-PROBE-0001-LONG";  // 35 bytes: 16 + 16 + 3
  uint8_t resp[32];
  uint8_t n = 0;
  CHECK_EQ(d.command(kSdepCmdAtWrapper, bytes(cmd).data(), static_cast<uint16_t>(cmd.size()), resp,
                     sizeof(resp), &n),
           kSdepOk);
  CHECK_EQ(nrf.commands.size(), 3u);
  CHECK(nrf.commands[0].more && nrf.commands[1].more && !nrf.commands[2].more);
  CHECK_EQ(nrf.commands[0].payload.size(), 16u);
  CHECK_EQ(nrf.commands[2].payload.size(), 3u);
  CHECK(nrf.at_commands.back() == cmd);
  CHECK(std::string(resp, resp + n) == "ERROR\r\n");
}

TEST(sdep_split_response_is_reassembled_and_capped) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  uint8_t resp[80];
  uint8_t n = 0;
  CHECK_EQ(d.command(kSdepCmdAtWrapper, bytes("ATI").data(), 3, resp, sizeof(resp), &n), kSdepOk);
  const std::string want = "BLEFRIEND32\r\nnRF51822 QFACA10\r\n0.7.7\r\nS110 8.0.0\r\nOK\r\n";
  CHECK(std::string(resp, resp + n) == want);  // 53 bytes = 4 packets
  CHECK_EQ(nrf.responses_pending(), 0u);
  // a smaller buffer keeps the first bytes and still drains every packet
  CHECK_EQ(d.command(kSdepCmdAtWrapper, bytes("ATI").data(), 3, resp, 10, &n), kSdepOk);
  CHECK_EQ(n, 10);
  CHECK(std::string(resp, resp + n) == want.substr(0, 10));
  CHECK_EQ(nrf.responses_pending(), 0u);
}

TEST(sdep_retries_while_module_not_ready) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  nrf.not_ready_transactions = 5;
  uint8_t resp[16];
  uint8_t n = 0;
  CHECK_EQ(d.command(kSdepCmdAtWrapper, bytes("AT").data(), 2, resp, sizeof(resp), &n), kSdepOk);
  CHECK(std::string(resp, resp + n) == "OK\r\n");
  CHECK_EQ(nrf.not_ready_transactions, 0);
}

TEST(sdep_error_reply_is_reported) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  uint8_t n = 0;
  CHECK_EQ(d.command(0x1234, nullptr, 0, nullptr, 0, &n), kSdepErrorReply);
  CHECK_EQ(d.last_error(), kSdepErrInvalidCommand);
  CHECK_EQ(nrf.responses_pending(), 0u);
}

TEST(sdep_absent_module_times_out_boundedly) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  nrf.present = false;
  SdepDriver d(nrf, clock);
  uint8_t resp[8];
  uint8_t n = 0;
  const uint32_t t0 = clock.now_us;
  CHECK_EQ(d.command(kSdepCmdAtWrapper, bytes("AT").data(), 2, resp, sizeof(resp), &n),
           kSdepTimeout);
  const uint32_t took = clock.now_us - t0;
  CHECK(took >= STIPI_SDEP_TIMEOUT_US);
  CHECK(took <= STIPI_SDEP_TIMEOUT_US + 1000);
  // a module stuck "not ready" also times out
  nrf.present = true;
  nrf.not_ready_transactions = 1000000;
  CHECK_EQ(d.command(kSdepCmdAtWrapper, bytes("AT").data(), 2, resp, sizeof(resp), &n),
           kSdepTimeout);
}

TEST(ble_link_resets_probes_and_becomes_ready) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  BleUartLink link(d, nrf, clock);
  link.begin();
  CHECK(nrf.reset_asserted);
  CHECK_EQ(nrf.resets, 1);
  settle(link, clock);
  CHECK(!nrf.reset_asserted);
  CHECK_EQ(link.state(), BleUartLink::kReady);
  CHECK(clock.now_us >= STIPI_BLE_RESET_PULSE_US + STIPI_BLE_BOOT_US);
  CHECK(link.connected());
  CHECK(link.is_open());
  CHECK(nrf.at_commands.size() >= 2u);
  CHECK(nrf.at_commands[0] == "AT");
  CHECK(nrf.at_commands[1] == "AT+GAPGETCONN");
  nrf.connected = false;
  clock.now_us += STIPI_BLE_CONN_POLL_US;
  link.poll();
  CHECK(!link.is_open());
  const uint8_t f[3] = {1, 2, 0};
  CHECK(!link.write_frame(f, 3));
}

TEST(ble_link_gives_up_on_absent_module_and_stays_quiet) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  nrf.present = false;
  SdepDriver d(nrf, clock);
  BleUartLink link(d, nrf, clock);
  link.begin();
  const uint32_t t0 = clock.now_us;
  settle(link, clock);
  CHECK_EQ(link.state(), BleUartLink::kAbsent);
  // reset + boot + one bounded timeout per probe attempt (plus the 1 ms settle steps)
  CHECK(clock.now_us - t0 <= STIPI_BLE_RESET_PULSE_US + STIPI_BLE_BOOT_US +
                                 STIPI_BLE_PROBE_ATTEMPTS * (STIPI_SDEP_TIMEOUT_US + 2000) + 5000);
  const uint32_t t1 = clock.now_us;
  for (int i = 0; i < 100; ++i) link.poll();
  CHECK_EQ(clock.now_us, t1);  // no more waiting
  CHECK(!link.is_open());
}

TEST(ble_link_writes_frames_in_16_byte_packets) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  BleUartLink link(d, nrf, clock);
  link.begin();
  settle(link, clock);
  nrf.commands.clear();
  std::vector<uint8_t> frame(39);
  for (size_t i = 0; i < frame.size(); ++i) frame[i] = static_cast<uint8_t>(i + 1);
  frame.back() = 0;
  CHECK(link.write_frame(frame.data(), 39));
  // first frame after connecting starts with a lone 0x00 (clears the central's partial frame)
  std::vector<uint8_t> expect(1, 0);
  expect.insert(expect.end(), frame.begin(), frame.end());
  CHECK(nrf.probe_to_central == expect);
  CHECK_EQ(nrf.commands.size(), 4u);
  if (nrf.commands.size() == 4) {
    CHECK(nrf.commands[1].more && nrf.commands[2].more && !nrf.commands[3].more);
    CHECK_EQ(nrf.commands[1].payload.size(), 16u);
    CHECK_EQ(nrf.commands[3].payload.size(), 7u);
  }
  // module buffer full on the first packet: nothing of the frame went out, no resync needed
  nrf.probe_to_central.clear();
  nrf.uart_tx_errors = 1;
  CHECK(!link.write_frame(frame.data(), 39));
  CHECK_EQ(link.tx_failures(), 1);
  CHECK(nrf.probe_to_central.empty());
  CHECK(link.write_frame(frame.data(), 39));
  CHECK(nrf.probe_to_central == frame);
}

TEST(ble_link_resyncs_after_a_fragment) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  BleUartLink link(d, nrf, clock);
  link.begin();
  settle(link, clock);
  std::vector<uint8_t> frame(39, 0x66);
  frame.back() = 0;
  CHECK(link.write_frame(frame.data(), 39));
  nrf.probe_to_central.clear();
  nrf.uart_tx_error_skip = 1;  // first packet accepted, second refused: a fragment is out
  nrf.uart_tx_errors = 1;
  CHECK(!link.write_frame(frame.data(), 39));
  CHECK_EQ(nrf.probe_to_central.size(), 16u);
  CHECK(link.write_frame(frame.data(), 39));
  // fragment, then a lone 0x00 that ends it (the host drops it as a bad frame), then the frame
  std::vector<uint8_t> expect(frame.begin(), frame.begin() + 16);
  expect.push_back(0);
  expect.insert(expect.end(), frame.begin(), frame.end());
  CHECK(nrf.probe_to_central == expect);
}

TEST(ble_link_receives_central_bytes) {
  fakes::FakeClock clock;
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  BleUartLink link(d, nrf, clock);
  link.begin();
  settle(link, clock);
  for (uint8_t i = 1; i <= 50; ++i) nrf.central_to_probe.push_back(i);
  std::vector<uint8_t> got;
  for (int pass = 0; pass < 20 && got.size() < 50; ++pass) {
    clock.now_us += STIPI_BLE_RX_POLL_US;
    link.poll();
    for (int16_t b = link.read(); b >= 0; b = link.read()) got.push_back(static_cast<uint8_t>(b));
  }
  CHECK_EQ(got.size(), 50u);
  for (size_t i = 0; i < got.size(); ++i) CHECK_EQ(got[i], i + 1);
}

TEST(probe_over_ble_answers_a_central) {
  fakes::FakeClock clock(1000);
  fakes::FakeNrf51 nrf(clock);
  SdepDriver d(nrf, clock);
  BleUartLink ble(d, nrf, clock);
  Sampler sampler;
  fakes::FakeBoard board(clock, sampler);
  fakes::FakeEeprom eeprom;
  Probe probe(clock, board, sampler, eeprom);
  probe.set_link(kLinkBle, &ble);
  ble.begin();
  probe.begin();
  settle(ble, clock);
  const std::vector<uint8_t> cmd = fakes::command_wire(77, kCmdGetInfo, {});
  nrf.central_to_probe.insert(nrf.central_to_probe.end(), cmd.begin(), cmd.end());
  for (int i = 0; i < 10; ++i) {
    clock.now_us += STIPI_BLE_RX_POLL_US;
    ble.poll();
    probe.poll();
  }
  const auto frames = fakes::take_frames(nrf.probe_to_central);
  bool acked = false;
  for (const auto& f : frames) {
    if (f.type == kMsgAck && get_u16(f.body.data()) == 77) acked = f.body[3] == kAckOk;
  }
  CHECK(acked);
  bool status_ble = false;
  for (const auto& f : frames) {
    if (f.type == kMsgStatus) status_ble = (f.body[9] & kFlagBleConnected) != 0;
  }
  CHECK(status_ble);
}

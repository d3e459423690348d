// test_sdep.cpp -- SDEP driver and BLE UART link against the simulated nRF51 (nrf51_sim, written
// from Adafruit's SDEP.md and checked with Adafruit's own driver in tests/firmware/vendor_driver).
#include <string>
#include <vector>

#include "../src/core/frame.h"
#include "../src/core/sdep.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

namespace {
struct Rig {
  fakes::FakeClock clock;
  fakes::SimNrf51Port port{clock};
  SdepDriver sdep{port, clock};
  BleUartLink link{sdep, port, clock};
  std::string central;  // bytes the central received
  uint32_t max_pass_us = 0;

  Rig() {
    port.m.on_notify = [](void* ctx, const uint8_t* d, uint16_t n) {
      static_cast<Rig*>(ctx)->central.append(reinterpret_cast<const char*>(d), n);
    };
    port.m.notify_ctx = this;
    link.begin();
  }
  // Main-loop passes, 100 us apart, for `us` microseconds; records the longest poll().
  void run(uint32_t us) {
    const uint32_t end = clock.now_us + us;
    while (static_cast<int32_t>(end - clock.now_us) > 0) {
      const uint32_t t0 = clock.now_us;
      link.poll();
      if (clock.now_us - t0 > max_pass_us) max_pass_us = clock.now_us - t0;
      clock.now_us += 100;
      port.sync();
    }
  }
  void boot() {
    nrf51_sim_set_connected(&port.m, 1);
    run(STIPI_BLE_RESET_PULSE_US + STIPI_BLE_BOOT_US + 100000);
  }
};

std::vector<uint8_t> frame_bytes(uint8_t len, uint8_t salt) {
  std::vector<uint8_t> f;
  for (uint8_t i = 0; i + 1 < len; ++i) f.push_back(static_cast<uint8_t>(1 + (i + salt) % 250));
  f.push_back(0);  // a COBS frame ends with its delimiter
  return f;
}
}  // namespace

TEST(ble_link_boots_with_echo_off_and_sees_the_central) {
  Rig r;
  r.boot();
  CHECK_EQ(r.link.state(), BleUartLink::kReady);
  CHECK_EQ(r.port.m.echo, 0);  // ATE=0 at start-up
  CHECK(r.link.connected());
  CHECK(r.link.is_open());
  CHECK_EQ(r.port.m.protocol_errors, 0u);
  CHECK(r.max_pass_us <= 1000);
}

TEST(ble_link_backs_off_from_an_absent_module_without_blocking) {
  Rig r;
  r.port.m.present = 0;
  r.run(STIPI_BLE_RESET_PULSE_US + STIPI_BLE_BOOT_US +
        STIPI_BLE_PROBE_ATTEMPTS * STIPI_SDEP_TIMEOUT_US + 20000);
  CHECK_EQ(r.link.state(), BleUartLink::kAbsent);
  CHECK_EQ(r.link.health(), kBleAbsent);
  CHECK(!r.link.is_open());
  CHECK(r.max_pass_us <= 1000);  // the probe waits across passes, never inside one
  const uint64_t bytes = r.port.bytes;
  r.run(STIPI_BLE_RETRY_MIN_US - 30000);
  CHECK_EQ(r.port.bytes, bytes);  // absent: no SPI traffic during the back-off
  // The module appears later (plugged, powered, or slow): the next retry resets and finds it.
  r.port.m.present = 1;
  nrf51_sim_set_connected(&r.port.m, 1);
  r.run(30000 + STIPI_BLE_RESET_PULSE_US + STIPI_BLE_BOOT_US + 100000);
  CHECK_EQ(r.link.state(), BleUartLink::kReady);
  CHECK_EQ(r.link.health(), kBleUp);
  CHECK_EQ(r.port.m.echo, 0);
  CHECK(r.max_pass_us <= 1000);
}

TEST(ble_link_back_off_doubles_up_to_its_limit_and_never_stops) {
  Rig r;
  r.port.m.present = 0;
  r.run(200000000UL);  // 200 s
  // begin(), then retries after 1, 2, 4, 8, 16, 32, 32 ... s (each plus ~1.5 s of boot wait
  // and probing): 1 + 9 resets in 200 s, and more for as long as it runs.
  CHECK_EQ(r.port.rst_pulses, 10u);
  CHECK(r.max_pass_us <= 1000);
}

TEST(ble_link_waits_for_a_module_that_boots_slowly) {
  // A module answering 0xFE for 1.6 s after reset is booting, not absent (SDEP.md, "SDEP
  // Packet and SPI Error Identifier"): 2,453 of those once made the link give up for good.
  // 3 s outlasts the boot wait and every probe the link makes for an absent module.
  for (uint32_t boot_us : {1600000u, 3000000u}) {
    Rig r;
    r.port.m.boot_us = boot_us;
    nrf51_sim_set_connected(&r.port.m, 1);
    bool ever_absent = false;
    for (int i = 0; i < 50; ++i) {
      r.run(100000);
      ever_absent = ever_absent || r.link.state() == BleUartLink::kAbsent;
      if (r.link.state() != BleUartLink::kReady) CHECK_EQ(r.link.health(), kBleBooting);
    }
    CHECK(!ever_absent);
    CHECK_EQ(r.port.rst_pulses, 1u);  // only begin(): never reset again as if absent
    CHECK(r.port.m.not_ready > 0u);   // it did answer "busy" on the way
    CHECK_EQ(r.link.state(), BleUartLink::kReady);
    CHECK(r.link.is_open());
    CHECK(r.max_pass_us <= 1000);
  }
}

TEST(ble_link_gives_up_on_a_module_busy_forever_and_retries) {
  Rig r;
  r.port.m.boot_us = 2000000000UL;  // 2000 s: 0xFE for the whole test
  r.run(STIPI_BLE_BOOT_MAX_US + 1000000);
  CHECK_EQ(r.link.state(), BleUartLink::kAbsent);  // reset again after the back-off
  r.port.m.boot_us = 1000;                         // the next reset works
  nrf51_sim_set_connected(&r.port.m, 1);
  r.run(STIPI_BLE_RETRY_MIN_US + STIPI_BLE_RESET_PULSE_US + STIPI_BLE_BOOT_US + 100000);
  CHECK_EQ(r.link.state(), BleUartLink::kReady);
}

TEST(ble_link_probes_again_after_the_module_restarts) {
  for (uint32_t boot_us : {5000u, 1600000u}) {  // quick restart (echo back on) and a slow one
    Rig r;
    r.boot();
    CHECK(r.link.is_open());
    CHECK_EQ(r.link.module_resets(), 0u);
    nrf51_sim_reset(&r.port.m, 1);  // the module resets itself (brown-out, its watchdog)
    nrf51_sim_set_connected(&r.port.m, 0);
    r.port.m.boot_us = boot_us;
    nrf51_sim_reset(&r.port.m, 0);
    nrf51_sim_set_connected(&r.port.m, 1);  // the central reconnects
    r.run(boot_us + 2 * STIPI_BLE_CONN_POLL_US + 3 * STIPI_SDEP_TIMEOUT_US);
    CHECK_EQ(r.link.module_resets(), 1u);
    CHECK_EQ(r.link.state(), BleUartLink::kReady);
    CHECK_EQ(r.port.m.echo, 0);  // ATE=0 again
    CHECK(r.link.is_open());
    CHECK(r.max_pass_us <= 1000);
  }
}

TEST(ble_link_sends_a_frame_as_one_command_with_one_response) {
  Rig r;
  r.boot();
  const uint32_t cmds = r.port.m.commands, in = r.port.m.packets_in, out = r.port.m.packets_out;
  r.central.clear();
  const std::vector<uint8_t> f = frame_bytes(39, 3);
  CHECK(r.link.write_frame(f.data(), 39));
  r.run(200000);
  CHECK_EQ(r.port.m.commands - cmds >= 1u, true);
  CHECK_EQ(r.port.m.packets_in - in - (r.port.m.commands - cmds - 1), 3u);  // 16 + 16 + 7
  CHECK(r.port.m.packets_out - out >= 1u);
  CHECK(r.central.find(std::string(f.begin(), f.end())) != std::string::npos);
  CHECK_EQ(r.port.m.protocol_errors, 0u);
  CHECK_EQ(r.port.m.unread_at_command, 0u);
}

TEST(ble_link_survives_processing_delays_and_stale_irq) {
  for (uint32_t delay_us : {0u, 1000u, 7000u, 20000u}) {
    Rig r;
    r.port.m.process_us = delay_us;
    r.port.m.irq_lag_us = 300;
    r.port.m.conn_interval_us = 7500;
    r.port.m.tx_per_event_b = 80;
    r.boot();
    CHECK_EQ(r.link.state(), BleUartLink::kReady);
    std::string sent;
    for (int k = 0; k < 20; ++k) {
      const std::vector<uint8_t> f = frame_bytes(static_cast<uint8_t>(20 + k * 3), static_cast<uint8_t>(k));
      CHECK(r.link.write_frame(f.data(), static_cast<uint8_t>(f.size())));
      sent.append(f.begin(), f.end());
      r.run(30000);
    }
    r.run(500000);
    CHECK(r.central.size() >= sent.size());
    CHECK(r.central.substr(r.central.size() - sent.size()) == sent);
    CHECK_EQ(r.link.frames_lost(), 0u);
    CHECK(r.max_pass_us <= 1000);
  }
}

TEST(ble_link_receives_central_bytes) {
  Rig r;
  r.boot();
  const std::string msg = "a command from the central, 3 packets";
  nrf51_sim_central_write(&r.port.m, reinterpret_cast<const uint8_t*>(msg.data()),
                          static_cast<uint16_t>(msg.size()));
  r.run(100000);
  std::string got;
  for (int16_t b = r.link.read(); b >= 0; b = r.link.read()) got += static_cast<char>(b);
  CHECK(got == msg);
}

TEST(ble_link_counts_frames_the_full_module_refused) {
  for (int old_firmware = 0; old_firmware <= 1; ++old_firmware) {
    Rig r;
    r.port.m.no_fifo_command = old_firmware;  // before 0.6.7: no AT+BLEUARTFIFO
    r.boot();
    r.port.m.tx_per_event_b = 0;  // the central stops reading
    uint32_t accepted = 0;
    for (int k = 0; k < 60; ++k) {
      const std::vector<uint8_t> f = frame_bytes(39, static_cast<uint8_t>(k));
      accepted += r.link.write_frame(f.data(), 39);
      r.run(20000);
    }
    r.run(1000000);
    CHECK(accepted < 60u);  // the ring refused the rest: seq gaps, counted
    CHECK(r.max_pass_us <= 1000);
    if (old_firmware) {
      CHECK(!r.link.fifo_flow_control());
      CHECK(r.port.m.tx_errors >= 1u);  // ERROR after ~200 ms of a full FIFO
      CHECK(r.link.tx_failures() >= 1u);
      CHECK(r.link.frames_lost() >= 1u);
      CHECK(accepted > r.link.frames_lost());
    } else {  // flow control: nothing sent that the FIFO has no room for
      CHECK(r.link.fifo_flow_control());
      CHECK_EQ(r.port.m.room_waits, 0u);
      CHECK_EQ(r.port.m.tx_errors, 0u);
      CHECK_EQ(r.link.frames_lost(), 0u);
      CHECK(r.port.m.tx_count + 39u > r.port.m.tx_fifo_cap_b);  // it filled the FIFO
    }
  }
}

TEST(ble_link_disconnect_and_reconnect) {
  Rig r;
  r.boot();
  nrf51_sim_set_connected(&r.port.m, 0);
  r.run(STIPI_BLE_CONN_POLL_US + 50000);
  CHECK(!r.link.is_open());
  const std::vector<uint8_t> f = frame_bytes(20, 1);
  CHECK(!r.link.write_frame(f.data(), 20));
  r.central.clear();
  nrf51_sim_set_connected(&r.port.m, 1);
  r.run(STIPI_BLE_CONN_POLL_US + 50000);
  CHECK(r.link.is_open());
  CHECK(r.link.write_frame(f.data(), 20));
  r.run(200000);
  CHECK(r.central.size() == 21u);
  CHECK_EQ(r.central[0], '\0');  // a new central starts on a frame boundary
}

// ---- the simulated module against SDEP.md (each test names the section it checks) ---------
// These hold the model to the spec where neither the vendor's driver nor the link would notice
// (tests/firmware/test_sim_mutations.py switches each violation on and expects a failure).
namespace {
struct Bench {  // the SDEP driver alone against the module, no link polling it
  fakes::FakeClock clock;
  fakes::SimNrf51Port port{clock};
  SdepDriver sdep{port, clock};
  Bench() { port.m.echo = 0; }
  void wait(uint32_t us) {
    clock.now_us += us;
    port.sync();
  }
  void send(uint16_t id, const std::string& payload) {  // all packets, back to back
    size_t at = 0;
    do {
      const size_t n = payload.size() - at > 16 ? 16 : payload.size() - at;
      const bool more = at + n < payload.size();
      CHECK_EQ(sdep.send_packet(id, reinterpret_cast<const uint8_t*>(payload.data()) + at,
                                static_cast<uint8_t>(n), more), kSdepOk);
      at += n;
    } while (at < payload.size());
  }
  // Every packet of one answer: (status, packet) until one without more-data.
  std::vector<SdepPacket> answer(SdepStatus* last) {
    std::vector<SdepPacket> got;
    for (int tries = 0; tries < 1000; ++tries) {
      SdepPacket p;
      const SdepStatus st = sdep.read_packet(p);
      *last = st;
      if (st == kSdepAgain) {
        wait(50);
        continue;
      }
      got.push_back(p);
      if (st != kSdepOk || !p.more) break;
    }
    return got;
  }
};
std::string text_of(const std::vector<SdepPacket>& ps) {
  std::string s;
  for (const SdepPacket& p : ps) s.append(reinterpret_cast<const char*>(p.payload), p.len);
  return s;
}
}  // namespace

TEST(nrf51_sim_answers_once_after_the_last_packet_with_irq_low_before) {
  // SDEP.md "Command Messages" (one answer, after the packet with More data == 0) and
  // "IRQ Pin" (asserted only while a whole packet waits).
  Bench b;
  nrf51_sim_set_connected(&b.port.m, 1);
  const std::string data(40, 'x');  // 3 packets
  b.send(kSdepCmdUartTx, data);
  CHECK(!b.port.irq());  // processing: nothing to read yet
  b.wait(b.port.m.process_us + 100);
  CHECK(b.port.irq());
  SdepStatus st;
  const std::vector<SdepPacket> a = b.answer(&st);
  CHECK_EQ(st, kSdepOk);
  CHECK_EQ(a.size(), 1u);
  CHECK_EQ(a[0].id, kSdepCmdUartTx);
  b.wait(100);  // past the IRQ's lag
  CHECK(!b.port.irq());
  CHECK_EQ(b.port.m.out_count, 0);
}

TEST(nrf51_sim_keeps_irq_high_between_packets_of_one_answer) {
  // SDEP.md "IRQ Pin": stays asserted while more packets wait; "Response Messages".
  Bench b;
  nrf51_sim_set_connected(&b.port.m, 1);
  const std::string msg = "central says hello over several SDEP packets!";  // 45 B
  nrf51_sim_central_write(&b.port.m, reinterpret_cast<const uint8_t*>(msg.data()),
                          static_cast<uint16_t>(msg.size()));
  b.send(kSdepCmdUartRx, "");
  b.wait(b.port.m.process_us + 100);
  SdepPacket p;
  CHECK_EQ(b.sdep.read_packet(p), kSdepOk);
  CHECK(p.more);
  CHECK(b.port.irq());  // the next packet is there: IRQ did not drop
  SdepStatus st;
  const std::vector<SdepPacket> rest = b.answer(&st);
  CHECK_EQ(st, kSdepOk);
  CHECK(std::string(reinterpret_cast<const char*>(p.payload), p.len) + text_of(rest) == msg);
}

TEST(nrf51_sim_answers_not_ready_while_busy) {
  // SDEP.md "SDEP Packet and SPI Error Identifier": 0xFE while the slave is not ready.
  Bench b;
  b.send(kSdepCmdAtWrapper, "ATI");
  const uint16_t before = b.sdep.not_ready_seen();
  const uint8_t x = 'A';
  CHECK_EQ(b.sdep.send_packet(kSdepCmdAtWrapper, &x, 1, false), kSdepAgain);  // busy: 0xFE
  CHECK_EQ(b.sdep.not_ready_seen(), before + 1);
  CHECK_EQ(b.port.m.commands, 0u);
}

TEST(nrf51_sim_unknown_command_gets_an_error_message) {
  // SDEP.md "Error Messages": type 0x80, error id 0x0001 Invalid Cmd ID.
  Bench b;
  b.send(0x1234, "x");
  b.wait(b.port.m.process_us + 100);
  SdepStatus st;
  const std::vector<SdepPacket> a = b.answer(&st);
  CHECK_EQ(st, kSdepErrorReply);
  CHECK_EQ(a.size(), 1u);
  CHECK_EQ(a.back().id, 0x0001);
}

TEST(nrf51_sim_answers_a_malformed_packet_with_invalid_payload) {
  // SDEP.md "Error Messages": 0x0003 Invalid Payload -- a packet announcing 20 bytes (> 16).
  Bench b;
  b.port.select(true);
  b.wait(100);  // "SPI Bus Hardware Requirements"
  b.port.transfer(kSdepCommand);
  b.port.transfer(0x00);
  b.port.transfer(0x0A);
  b.port.transfer(20);
  for (int i = 0; i < 16; ++i) b.port.transfer('A');
  b.port.select(false);
  b.wait(100);
  SdepStatus st;
  const std::vector<SdepPacket> a = b.answer(&st);
  CHECK_EQ(st, kSdepErrorReply);
  CHECK(!a.empty() && a.back().id == 0x0003);
}

TEST(nrf51_sim_keeps_an_unread_answer_when_a_new_command_comes) {
  // SDEP.md "SDEP Data Transactions": every command gets its answer.
  Bench b;
  b.send(kSdepCmdAtWrapper, "AT");
  b.wait(b.port.m.process_us + 100);  // answered, not read
  b.send(kSdepCmdAtWrapper, "ATI");
  b.wait(b.port.m.process_us + 100);
  SdepStatus st;
  CHECK(text_of(b.answer(&st)) == "OK\r\n");  // the first answer, first
  CHECK(text_of(b.answer(&st)).find("BLEFRIEND32") == 0);
}

TEST(nrf51_sim_refuses_uart_tx_without_a_central) {
  // Nothing to notify: the module answers ERROR rather than drop the bytes as sent.
  Bench b;
  b.send(kSdepCmdUartTx, "hello");
  b.wait(b.port.m.process_us + 100);
  SdepStatus st;
  CHECK(text_of(b.answer(&st)) == "ERROR\r\n");
}

TEST(nrf51_sim_ignores_bytes_clocked_before_the_cs_setup_time) {
  // SDEP.md "SPI Bus Hardware Requirements": 100 us from CS asserted to the first byte.
  Bench b;
  b.port.select(true);
  CHECK_EQ(b.port.transfer(kSdepCommand), kSdepNotReady);  // too early: not ready
  for (int i = 0; i < 5; ++i) b.port.transfer(0x41);
  b.port.select(false);
  CHECK_EQ(b.port.m.packets_in, 0u);
  CHECK_EQ(b.port.m.cs_early, 1u);
  b.send(kSdepCmdAtWrapper, "AT");  // with the 100 us: taken
  CHECK_EQ(b.port.m.packets_in, 1u);
}

TEST(nrf51_sim_sends_alerts_and_the_link_skips_them) {
  // SDEP.md "Alert Messages": 0x40, alert id, payload (0x0002 Battery Low).
  Bench b;
  const uint8_t level = 7;
  nrf51_sim_alert(&b.port.m, 0x0002, &level, 1);
  CHECK(b.port.irq());
  SdepPacket p;
  CHECK_EQ(b.sdep.read_packet(p), kSdepOk);
  CHECK_EQ(p.type, kSdepAlert);
  CHECK_EQ(p.id, 0x0002);
  CHECK(p.len == 1 && p.payload[0] == 7);
  // An alert in the middle of a stream is not an answer: the link carries on.
  Rig r;
  r.boot();
  nrf51_sim_alert(&r.port.m, 0x0002, &level, 1);
  r.run(STIPI_BLE_CONN_POLL_US + 100000);
  CHECK(r.link.is_open());
  CHECK_EQ(r.link.stale_answers(), 0u);
  CHECK_EQ(r.link.module_resets(), 0u);
  CHECK_EQ(r.port.m.alerts, 1u);
}

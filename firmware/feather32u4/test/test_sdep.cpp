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
  Rig r;
  r.port.m.boot_us = 1600000;
  nrf51_sim_set_connected(&r.port.m, 1);
  bool ever_absent = false;
  for (int i = 0; i < 40; ++i) {
    r.run(100000);
    ever_absent = ever_absent || r.link.state() == BleUartLink::kAbsent;
    if (r.link.state() != BleUartLink::kReady) CHECK_EQ(r.link.health(), kBleBooting);
  }
  CHECK(!ever_absent);
  CHECK(r.port.m.not_ready > 0u);  // it did answer "busy" on the way
  CHECK_EQ(r.link.state(), BleUartLink::kReady);
  CHECK(r.link.is_open());
  CHECK(r.max_pass_us <= 1000);
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
  CHECK_EQ(r.port.m.responses_discarded, 0u);
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

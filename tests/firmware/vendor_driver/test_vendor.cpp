// test_vendor.cpp -- Adafruit's own SPI driver (Adafruit_BluefruitLE_SPI, compiled from
// ../shared/reference) against the simulated nRF51. If the vendor's driver fails here, the
// simulated module is wrong: it is the check that nrf51_sim follows the vendor, not our firmware.
#include <stdio.h>
#include <stdlib.h>

#include <string>

#include "Adafruit_BluefruitLE_SPI.h"
#include "shim.h"

namespace {
int g_failed = 0, g_checks = 0;
std::string g_central;  // bytes the central received

#define EXPECT(cond)                                                   \
  do {                                                                 \
    ++g_checks;                                                        \
    if (!(cond)) {                                                     \
      ++g_failed;                                                      \
      printf("FAIL %s:%d: %s\n", __FILE__, __LINE__, #cond);           \
    }                                                                  \
  } while (0)

void on_notify(void*, const uint8_t* d, uint16_t n) { g_central.append((const char*)d, n); }

void drain_tx() {
  for (int i = 0; i < 2000 && shim::g_module.tx_count; ++i) delay(1);
}

std::string pattern(size_t n, size_t salt) {
  std::string s;
  for (size_t i = 0; i < n; ++i) s += static_cast<char>('a' + (i + salt) % 26);
  return s;
}

void test_uart_tx(Adafruit_BluefruitLE_SPI& ble) {
  std::string sent;
  for (size_t n = 1; n <= 200; ++n) {
    const std::string s = pattern(n, n);
    const uint32_t cmds = shim::g_module.commands;
    EXPECT(ble.print(s.c_str()) == n);
    EXPECT(shim::g_module.commands == cmds + 1);  // one command, however many packets
    sent += s;
    drain_tx();
  }
  EXPECT(g_central == sent);
  EXPECT(shim::g_module.tx_errors == 0);
  printf("uart tx: %zu bytes in 200 prints of 1-200 bytes, %u packets in\n", sent.size(),
         (unsigned)shim::g_module.packets_in);
}

void test_uart_rx(Adafruit_BluefruitLE_SPI& ble) {
  const std::string msg = "central says hello over several SDEP packets!";  // 45 B: 3 packets
  nrf51_sim_central_write(&shim::g_module, (const uint8_t*)msg.data(), (uint16_t)msg.size());
  std::string got;
  for (int i = 0; i < 200 && got.size() < msg.size(); ++i) {
    while (ble.available()) got += static_cast<char>(ble.read());
  }
  EXPECT(got == msg);
  EXPECT(ble.available() == 0);
}

void test_full_fifo(Adafruit_BluefruitLE_SPI& ble) {
  shim::g_module.tx_per_event_b = 0;  // the central stops reading: the FIFO fills up
  const std::string s = pattern(200, 0);
  const uint32_t t0 = shim::g_now_us;
  for (int i = 0; i < 7; ++i) ble.print(s.c_str());  // 1400 B > 1024 B
  EXPECT(shim::g_module.tx_errors >= 1);              // the module answered ERROR...
  EXPECT(shim::g_now_us - t0 >= 200000u);             // ...after ~200 ms, driver carried on
  shim::g_module.tx_per_event_b = 80;
  drain_tx();
}
}  // namespace

int main() {
  nrf51_sim_init(&shim::g_module);
  shim::g_module.boot_us = 900000;  // the vendor's begin() waits 1 s after RST
  shim::g_module.process_us = 5000;
  shim::g_module.conn_interval_us = 7500;
  shim::g_module.tx_per_event_b = 80;  // 4 notifications of 20 B per event
  shim::g_module.on_notify = on_notify;
  Adafruit_BluefruitLE_SPI ble(shim::kPinCs, shim::kPinIrq, shim::kPinRst);

  EXPECT(ble.begin(false, true));
  EXPECT(shim::g_module.echo == 1);
  EXPECT(ble.sendCommandCheckOK("AT"));  // with echo on: "AT\r\nOK\r\n"
  EXPECT(ble.echo(false));
  EXPECT(shim::g_module.echo == 0);
  EXPECT(!ble.isConnected());
  nrf51_sim_set_connected(&shim::g_module, 1);
  EXPECT(ble.isConnected());
  EXPECT(!ble.sendCommandCheckOK("AT+NOSUCHCOMMAND=1234567890"));  // 2 packets, one ERROR
  const uint32_t before = shim::g_module.packets_in;
  ble.println("AT+GAPGETCONN");  // 13 B + CRLF -> one packet
  EXPECT(ble.waitForOK());
  EXPECT(shim::g_module.packets_in == before + 1);

  ble.setMode(BLUEFRUIT_MODE_DATA);
  test_uart_tx(ble);
  test_uart_rx(ble);
  test_full_fifo(ble);
  ble.setMode(BLUEFRUIT_MODE_COMMAND);
  EXPECT(ble.isConnected());
  nrf51_sim_set_connected(&shim::g_module, 0);
  EXPECT(!ble.isConnected());
  EXPECT(shim::g_module.protocol_errors == 0);

  printf("module: %u commands, %u packets in, %u out, %u not-ready, %u over-reads\n",
         (unsigned)shim::g_module.commands, (unsigned)shim::g_module.packets_in,
         (unsigned)shim::g_module.packets_out, (unsigned)shim::g_module.not_ready,
         (unsigned)shim::g_module.overreads);
  printf("vendor driver: %d checks, %d failed\n", g_checks, g_failed);
  return g_failed ? 1 : 0;
}

// shim.cpp -- simulated time and pins behind Arduino.h / SPI.h, wired to one nrf51_sim.
#include "shim.h"

#include "Arduino.h"
#include "SPI.h"

HostSerial Serial;
SPIClass SPI;

namespace shim {
nrf51_sim g_module;
uint32_t g_now_us = 0;
static bool g_cs_low = false;

void tick(uint32_t us) {
  g_now_us += us;
  nrf51_sim_advance(&g_module, g_now_us);
}
}  // namespace shim

using shim::tick;

// Every poll of time or a pin costs a little simulated time, so busy-wait loops advance.
uint32_t millis() {
  tick(2);
  return shim::g_now_us / 1000;
}
uint32_t micros() {
  tick(2);
  return shim::g_now_us;
}
void delay(uint32_t ms) { tick(ms * 1000); }
void delayMicroseconds(uint32_t us) { tick(us); }
void pinMode(int, int) {}

void digitalWrite(int pin, int value) {
  tick(1);
  if (pin == shim::kPinCs) {
    const bool low = value == LOW;
    if (low != shim::g_cs_low) nrf51_sim_select(&shim::g_module, low ? 1 : 0);
    shim::g_cs_low = low;
  } else if (pin == shim::kPinRst) {
    nrf51_sim_reset(&shim::g_module, value == LOW ? 1 : 0);
  }
}

int digitalRead(int pin) {
  tick(2);
  return pin == shim::kPinIrq ? nrf51_sim_irq(&shim::g_module) : LOW;
}

// 8 bits at 4 MHz (the vendor's SPISettings) plus loop overhead: 3 us per byte.
uint8_t SPIClass::transfer(uint8_t out) {
  tick(3);
  return nrf51_sim_xfer(&shim::g_module, out);
}

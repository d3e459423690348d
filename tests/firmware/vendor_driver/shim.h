// shim.h -- the test's handle on the simulated world behind the Arduino shim.
#ifndef STIPI_SHIM_H
#define STIPI_SHIM_H
#include <stdint.h>

#include "nrf51_sim.h"

namespace shim {
const int kPinCs = 8;   // Feather 32u4 Bluefruit LE (hardware.md)
const int kPinIrq = 7;
const int kPinRst = 4;
extern nrf51_sim g_module;
extern uint32_t g_now_us;
void tick(uint32_t us);
}  // namespace shim
#endif

// SPI.h -- host SPI master for the shim: bytes go to the simulated nRF51 (nrf51_sim.h).
#ifndef STIPI_SHIM_SPI_H
#define STIPI_SHIM_SPI_H

#include "Arduino.h"

#define MSBFIRST 1
#define SPI_MODE0 0

struct SPISettings {
  SPISettings(uint32_t, uint8_t, uint8_t) {}
};

class SPIClass {
 public:
  void begin() {}
  void end() {}
  void beginTransaction(const SPISettings&) {}
  void endTransaction() {}
  uint8_t transfer(uint8_t out);
};
extern SPIClass SPI;

#endif

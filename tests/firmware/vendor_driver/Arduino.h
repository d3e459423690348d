// Arduino.h -- the minimal Arduino API Adafruit's BluefruitLE nRF51 library needs, on the host.
//
// Ours (tests only): simulated time (every call that polls advances it a little, so the
// vendor's busy-wait loops make progress), pins wired to the simulated nRF51 (nrf51_sim.h),
// and Print/Stream with the overloads the library calls. No vendor code lives here.
#ifndef STIPI_SHIM_ARDUINO_H
#define STIPI_SHIM_ARDUINO_H

#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef bool boolean;
typedef uint8_t byte;

#define HIGH 1
#define LOW 0
#define INPUT 0
#define OUTPUT 1
#define EOF (-1)
#define highByte(w) ((uint8_t)((w) >> 8))
#define lowByte(w) ((uint8_t)((w)&0xff))
#define HEX 16
#define bit(b) (1UL << (b))
#define bitRead(value, bit) (((value) >> (bit)) & 0x01)
inline uint16_t word(uint8_t h, uint8_t l) { return (uint16_t)((h << 8) | l); }

class __FlashStringHelper;
#define F(s) (reinterpret_cast<const __FlashStringHelper*>(s))

uint32_t millis();
uint32_t micros();
void delay(uint32_t ms);
void delayMicroseconds(uint32_t us);
void pinMode(int pin, int mode);
void digitalWrite(int pin, int value);
int digitalRead(int pin);

class Print {
 public:
  virtual ~Print() {}
  virtual size_t write(uint8_t c) = 0;
  virtual size_t write(const uint8_t* buf, size_t n) {
    size_t k = 0;
    while (n--) k += write(*buf++);
    return k;
  }
  size_t write(const char* s) { return write(reinterpret_cast<const uint8_t*>(s), strlen(s)); }
  virtual void flush() {}
  size_t print(const char* s) { return write(s); }
  size_t print(const __FlashStringHelper* s) { return print(reinterpret_cast<const char*>(s)); }
  size_t print(char c) { return write(static_cast<uint8_t>(c)); }
  size_t print(long v) { return print_int(v); }
  size_t print(unsigned long v, int base) { return base == 16 ? print_hex(v) : print_uint(v); }
  size_t print(int v) { return print_int(v); }
  size_t print(unsigned long v) { return print_uint(v); }
  size_t print(unsigned int v) { return print_uint(v); }
  size_t print(unsigned char v) { return print_uint(v); }
  size_t print(signed char v) { return print_int(v); }
  size_t print(short v) { return print_int(v); }
  size_t print(unsigned short v) { return print_uint(v); }
  size_t println() { return write(reinterpret_cast<const uint8_t*>("\r\n"), 2); }
  size_t println(unsigned long v, int base) { return print(v, base) + println(); }
  template <typename T>
  size_t println(T v) {
    const size_t n = print(v);
    return n + println();
  }

 private:
  size_t print_uint(unsigned long v) {
    char b[24];
    int i = 23;
    b[i] = 0;
    do {
      b[--i] = static_cast<char>('0' + v % 10);
      v /= 10;
    } while (v);
    return write(b + i);
  }
  size_t print_hex(unsigned long v) {
    char b[24];
    int i = 23;
    b[i] = 0;
    do {
      b[--i] = "0123456789ABCDEF"[v & 15];
      v >>= 4;
    } while (v);
    return write(b + i);
  }
  size_t print_int(long v) { return v < 0 ? print('-') + print_uint(-v) : print_uint(v); }
};

class Stream : public Print {
 protected:
  unsigned long _timeout = 1000;

 public:
  virtual int available() = 0;
  virtual int read() = 0;
  virtual int peek() = 0;
  size_t readBytes(char* buf, size_t n) {
    size_t k = 0;
    while (k < n) {
      const int c = read();
      if (c < 0) break;
      buf[k++] = static_cast<char>(c);
    }
    return k;
  }
  size_t readBytes(uint8_t* buf, size_t n) { return readBytes(reinterpret_cast<char*>(buf), n); }
};

class HostSerial : public Print {
 public:
  size_t write(uint8_t) override { return 1; }  // debug output is discarded
};
extern HostSerial Serial;

#endif

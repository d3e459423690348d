// usb_core_model.h -- the Arduino AVR core's USB CDC transmit path, as a host model.
//
// Written from the Arduino core's own code (Debian arduino-core-avr,
// /usr/share/arduino/hardware/arduino/avr/cores/arduino: USBCore.cpp USB_SendSpace, USB_Send,
// USB_Flush, ISR(USB_GEN_vect); CDC.cpp Serial_::availableForWrite, Serial_::write), not from
// the probe firmware. Each function below names the one it follows and keeps its control flow.
// The ATmega32u4's double-banked IN endpoint (datasheet 22.13/22.18) is modelled as: the
// current bank the CPU fills (FifoByteCount = UEBCLX), and the banks released to the USB
// controller (ReleaseTX: FIFOCON cleared) that the host has not read yet; RWAL is set while a
// bank is free for the CPU, i.e. fewer than 2 banks are waiting for the host.
//
// Time: a model clock in microseconds. The SOF interrupt is due at every 1 ms frame boundary;
// it runs (USB_Flush(CDC_TX)) at the points where the core's code has interrupts enabled --
// between calls, inside USB_Send between USB_SendSpace() and the LockEP block, and during
// delay(1) -- unless the SOF interrupt is disabled (UDIEN.SOFE clear), in which case it stays
// pending until it is enabled again. The host takes released banks (oldest first, up to
// packets_per_frame) in the frames where it reads.
#ifndef USB_CORE_MODEL_H
#define USB_CORE_MODEL_H

#include <stdint.h>

#include <deque>
#include <functional>
#include <vector>

namespace usbmodel {

const int kEpSize = 64;  // USBAPI.h USB_EP_SIZE; CDC_TX is EP_DOUBLE_64

class UsbCdcModel {
 public:
  // ---- the host side ----
  // Whether the host reads IN packets during the frame starting at `frame_ms`.
  std::function<bool(uint32_t frame_ms)> host_reads = [](uint32_t) { return true; };
  std::vector<uint8_t> received;  // bytes the host got, in order (ZLPs carry none)
  int packets_per_frame = 1;      // IN transactions the host completes in a frame it reads

  // ---- statistics ----
  uint32_t wait_ms = 0;        // USB_Send's delay(1) calls: the main loop stood still
  uint32_t send_failures = 0;  // USB_Send returned -1
  uint32_t failed_after_queuing = 0;  // ... after it had put bytes in a bank (they still go)
  uint32_t zlps = 0;

  uint32_t now_us = 0;
  bool configured = true;      // _usbConfiguration
  bool line_open = true;       // _usbLineInfo.lineState > 0 (DTR)
  bool sofe = true;            // UDIEN.SOFE

  // Let model time pass to `t_us` (interrupts enabled): frames, SOF, the host's reads.
  void advance_to(uint32_t t_us) {
    while (static_cast<int32_t>(t_us - next_frame_us_) >= 0) {
      now_us = next_frame_us_;
      next_frame_us_ += 1000;
      host_frame(now_us / 1000);
      sof_pending_ = true;
      interrupt_window();
    }
    now_us = t_us;
  }
  void cpu_us(uint32_t us) { advance_to(now_us + us); }

  // CDC.cpp Serial_::availableForWrite -> USBCore.cpp USB_SendSpace(CDC_TX).
  int available_for_write() { return USB_SendSpace(); }

  // CDC.cpp Serial_::write(const uint8_t*, size_t).
  size_t write(const uint8_t* buffer, size_t size) {
    if (line_open) {
      const int r = USB_Send(buffer, static_cast<int>(size));
      if (r > 0) return static_cast<size_t>(r);
      return 0;  // setWriteError()
    }
    return 0;
  }

  // The SOF interrupt enable (UDIEN.SOFE); a pending SOF runs as soon as it is set again.
  void set_sofe(bool on) {
    sofe = on;
    interrupt_window();
  }

 private:
  // USBCore.cpp USB_SendSpace: LockEP; if (!ReadWriteAllowed()) return 0;
  // return USB_EP_SIZE - FifoByteCount();
  int USB_SendSpace() {
    if (!rwal()) return 0;
    return kEpSize - static_cast<int>(current_.size());
  }

  // USBCore.cpp USB_Send(ep = CDC_TX, d, len), control flow kept line by line.
  int USB_Send(const uint8_t* data, int len) {
    if (!configured) return -1;
    const int r = len;
    uint8_t timeout = 250;  // "250ms timeout on send? TODO"
    bool send_zlp = false;
    bool queued_any = false;
    while (len || send_zlp) {
      int n = USB_SendSpace();
      if (n == 0) {
        if (!(--timeout)) {
          ++send_failures;
          if (queued_any) ++failed_after_queuing;
          return -1;
        }
        delay_1ms();
        continue;
      }
      if (n > len) n = len;
      interrupt_window();  // between USB_SendSpace's LockEP and this one: SOF may run
      {                    // LockEP lock(ep): interrupts off
        if (!rwal()) continue;  // "Frame may have been released by the SOF interrupt handler"
        len -= n;
        while (n--) {
          current_.push_back(*data++);  // Send8
          queued_any = true;
        }
        cpu_only(1);  // the bytes take the CPU about a microsecond or so each: interrupts off
        if (send_zlp) {
          release_tx();
          send_zlp = false;
        } else if (!rwal_after_write()) {  // "...release if buffer is full..."
          release_tx();
          if (len == 0) send_zlp = true;
        }
        // (TRANSFER_RELEASE is not set for CDC_TX)
      }
    }
    return r;
  }

  // USBCore.cpp USB_Flush(CDC_TX), run by ISR(USB_GEN_vect) on SOFI.
  void USB_Flush() {
    if (rwal() && !current_.empty()) release_tx();
  }

  // RWAL: the current bank can take bytes. After the CPU fills it (64 bytes) RWAL clears.
  bool rwal() const { return waiting_.size() < 2 && current_.size() < kEpSize; }
  bool rwal_after_write() const { return current_.size() < kEpSize; }
  // ReleaseTX: FIFOCON = 0, the bank (even empty: a zero-length packet) goes to the host.
  void release_tx() {
    if (current_.empty()) ++zlps;
    waiting_.push_back(current_);
    current_.clear();
  }
  void host_frame(uint32_t frame_ms) {
    if (!host_reads(frame_ms)) return;
    for (int k = 0; k < packets_per_frame && !waiting_.empty(); ++k) {
      received.insert(received.end(), waiting_.front().begin(), waiting_.front().end());
      waiting_.pop_front();
    }
  }
  void interrupt_window() {
    if (sof_pending_ && sofe) {
      sof_pending_ = false;
      USB_Flush();
    }
  }
  void delay_1ms() {  // wiring.c delay(1): interrupts run meanwhile
    ++wait_ms;
    advance_to(now_us + 1000);
  }
  void cpu_only(uint32_t us) {  // time passes with interrupts off (SOF stays pending)
    const bool s = sofe;
    sofe = false;
    advance_to(now_us + us);
    sofe = s;
  }

  std::vector<uint8_t> current_;
  std::deque<std::vector<uint8_t>> waiting_;
  uint32_t next_frame_us_ = 1000;
  bool sof_pending_ = false;
};

}  // namespace usbmodel

#endif

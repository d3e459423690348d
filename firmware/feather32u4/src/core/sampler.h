// sampler.h -- ring buffer between the sampling ISR and the main loop.
//
// Owns: the sample index (every sample taken since boot, queued or not), the dropped count, the
// ring of raw ADC values and the timestamp arithmetic of a batch. Does not own the timer/ADC
// (board glue) or framing (probe.cpp).
//
// Overflow policy: when the ring is full, the new sample is dropped, and so is every following
// sample until the main loop has emptied the ring ("drop until empty"). The ring therefore
// always holds consecutive indices, one (index, time) anchor describes all of it, and each
// overflow episode shows up on the host as one gap in first_index, matched by STATUS.dropped.
// Timestamps: the time of the sample that enters an empty ring is stored; the k-th sample after
// it was taken at t + k * period_us (both clocks run from the same resonator).
#ifndef STIPI_CORE_SAMPLER_H
#define STIPI_CORE_SAMPLER_H

#include <stdint.h>

#include "../../config.h"

namespace stipi {

struct Batch {
  uint32_t first_index;  // sample index of adc[0]
  uint32_t t_us;         // micros() when adc[0] was taken
  uint16_t period_us;    // sampling period [us]
  uint8_t count;
  uint16_t adc[STIPI_BATCH_SIZE > STIPI_TARE_SAMPLES ? STIPI_BATCH_SIZE : STIPI_TARE_SAMPLES];
};

class Sampler {
 public:
  static const uint8_t kCapacity = STIPI_RING_CAPACITY;

  Sampler();

  // Main loop, before the timer starts: the period that following samples are taken at [us].
  void set_period(uint16_t period_us);
  uint16_t period_us() const { return period_us_; }

  // --- interrupt context (or with interrupts disabled) -----------------------------------
  // A conversion finished: `adc` taken at `t_us`.
  void isr_push(uint16_t adc, uint32_t t_us);
  // A sample instant passed without a conversion (ADC busy): counted as taken and dropped.
  void isr_drop();

  // --- main loop (each takes a critical section) ------------------------------------------
  uint8_t available() const;
  // Dropping until the ring is empty: the consumer should drain it, partial batch included.
  bool overflowing() const;
  // Move up to `max` (<= size of Batch::adc) oldest samples into `out`; returns out.count.
  uint8_t pop(Batch& out, uint8_t max);
  void clear();              // discard everything queued (no index change)
  uint32_t dropped() const;  // samples lost in the probe since boot
  uint32_t taken() const;    // samples taken since boot = index of the next sample

 private:
  volatile uint16_t ring_[kCapacity];
  volatile uint8_t head_;    // next write slot
  volatile uint8_t count_;
  volatile bool overflow_;   // dropping until the ring is empty
  volatile uint32_t taken_;
  volatile uint32_t dropped_;
  volatile uint32_t first_index_;  // index of the oldest queued sample
  volatile uint32_t first_t_us_;   // time of the oldest queued sample
  uint16_t period_us_;
};

}  // namespace stipi

#endif

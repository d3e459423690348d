// oversample.h -- load-cell oversampling and ratiometric supply correction, pure arithmetic.
//
// Owns: how many conversions fit one sample period (oversample_log2), turning the sum of those
// conversions into one SAMPLES.adc value of STIPI_ADC_OUT_BITS bits with the supply correction
// applied (oversample_output), and the correction gain from a 5 V measurement (supply_gain_q14).
// Does not own the ADC (src/hal_avr.cpp runs the conversions from the Timer1/ADC interrupts).
//
// Oversampling: N = 2^k conversions taken back to back from the sample instant (each 104 us at
// the 125 kHz ADC clock) are summed. Their mean, scaled to STIPI_ADC_OUT_BITS bits and rounded,
// is the sample: with STIPI_ADC_EXTRA_BITS = 0 the wire keeps 10-bit counts (averaging removes
// noise, 1 count steps remain); with 2, 16 conversions give 12-bit counts (GET_INFO adc_bits).
//
// Ratiometric correction: the FC22's output is proportional to its 5 V supply, the ADC's to its
// 3.3 V reference. When the 5 V rail is measured through a divider on the same ADC (config.h
// STIPI_PIN_SUPPLY5), reading/supply_reading is independent of both voltages, so every sample is
// scaled by nominal_counts/measured_counts (Q14 gain). Without it the gain is 1 and STATUS.flags
// bit 4 says the force is not supply-corrected.
#ifndef STIPI_CORE_OVERSAMPLE_H
#define STIPI_CORE_OVERSAMPLE_H

#include <stdint.h>

#include "../../config.h"

namespace stipi {

const uint16_t kGainOne = 1u << 14;  // Q14 gain of 1.0

// log2 of the conversions per sample: the largest power of two <= STIPI_OVERSAMPLE_MAX such
// that those conversions plus one supply conversion (STIPI_ADC_CONV_BUDGET_US each) plus
// STIPI_ADC_MARGIN_US fit the period: 16 up to 486 Hz, 8 up to 881 Hz, 4 above. (Without the
// margin, 500 Hz with 16 lost the sample after each supply reading in simavr.)
inline uint8_t oversample_log2(uint16_t period_us) {
  uint8_t k = 0;
  while ((2u << k) <= STIPI_OVERSAMPLE_MAX &&
         static_cast<uint32_t>((2u << k) + 1u) * STIPI_ADC_CONV_BUDGET_US + STIPI_ADC_MARGIN_US <=
             period_us) {
    ++k;
  }
  return k;
}

// Whether the supply reading may be chained now, after a sample's last conversion, `since_us`
// after that sample's instant, the next instant coming `period_us` after it [us]. The next
// instant's timer interrupt outranks the ADC's: if the supply conversion has not landed by then,
// the timer finds the ADC busy and loses that sample. The margin in oversample_log2 is meant for
// this, but the interrupt latency spent in the sample's own conversions can use it up (at 486 Hz,
// a sample every ~40 heartbeats was lost in simavr), so the clock decides: the reading goes
// ahead only if its conversion ends STIPI_ADC_SUPPLY_SLACK_US before the next instant, and never
// once that instant has passed (`instant_passed`: its flag is pending). Otherwise it stays
// wanted and is tried after the next sample.
inline bool supply_fits(uint16_t since_us, uint16_t period_us, bool instant_passed) {
  return !instant_passed && static_cast<uint32_t>(since_us) + STIPI_ADC_CONV_BUDGET_US +
                                    STIPI_ADC_SUPPLY_SLACK_US <=
                                period_us;
}

// Offset from the sample instant (Timer1 compare) to the middle of its 2^log2n conversions
// [us]: the mean of a linearly changing input is its value there, so that is the sample's
// timestamp. Conversions are STIPI_ADC_CONV_PERIOD_US apart (104 us + the ISR's restart).
inline uint16_t oversample_center_us(uint8_t log2n) {
  return static_cast<uint16_t>((((1u << log2n) - 1u) * STIPI_ADC_CONV_PERIOD_US + 1u) / 2u);
}

// One sample from the sum of 2^log2n conversions and the Q14 supply gain, rounded, clipped to
// STIPI_ADC_OUT_BITS bits.
inline uint16_t oversample_output(uint32_t sum, uint8_t log2n, uint16_t gain_q14) {
  uint32_t v = (sum * gain_q14 + (1u << 13)) >> 14;  // sum <= 16 * 1023 < 2^14: no overflow
  const int8_t shift = static_cast<int8_t>(log2n - STIPI_ADC_EXTRA_BITS);
  if (shift > 0) {
    v = (v + (1u << (shift - 1))) >> shift;
  } else {
    v <<= -shift;
  }
  const uint32_t max = (1u << STIPI_ADC_OUT_BITS) - 1;
  return static_cast<uint16_t>(v > max ? max : v);
}

// Millivolts of the 5 V rail for a raw 10-bit reading of its divider.
inline uint32_t supply5_mv_of_raw(uint16_t raw) {
  return static_cast<uint32_t>((static_cast<uint32_t>(raw) * STIPI_SUPPLY5_DIVIDER * STIPI_ADC_REF_MV) >>
                               STIPI_ADC_BITS);
}

// Q14 gain nominal/measured for a raw supply-divider reading; kGainOne (and false) when the
// reading is implausible (outside STIPI_SUPPLY5_MIN_MV..STIPI_SUPPLY5_MAX_MV).
inline bool supply_gain_q14(uint16_t raw, uint16_t* gain) {
  const uint32_t mv = supply5_mv_of_raw(raw);
  if (mv < STIPI_SUPPLY5_MIN_MV || mv > STIPI_SUPPLY5_MAX_MV) {
    *gain = kGainOne;
    return false;
  }
  *gain = static_cast<uint16_t>((STIPI_SUPPLY5_NOMINAL_MV * kGainOne + mv / 2) / mv);
  return true;
}

}  // namespace stipi

#endif  // STIPI_CORE_OVERSAMPLE_H

// test_oversample.cpp -- conversions per sample, averaging to the wire's bits, supply gain.
#include "../src/core/oversample.h"
#include "runner.h"

using namespace stipi;

TEST(oversample_count_fits_the_period) {
  CHECK_EQ(oversample_log2(62500), 4);  // 16 Hz: 16 conversions
  CHECK_EQ(oversample_log2(10000), 4);  // 100 Hz
  CHECK_EQ(oversample_log2(2058), 4);   // 486 Hz: 17 * 115 + 100 = 2055 us
  CHECK_EQ(oversample_log2(2000), 3);   // 500 Hz: 8
  CHECK_EQ(oversample_log2(1135), 3);   // 881 Hz: 9 * 115 + 100 = 1135 us
  CHECK_EQ(oversample_log2(1111), 2);   // 900 Hz: 4
  CHECK_EQ(oversample_log2(1000), 2);   // 1000 Hz: 4
  for (uint32_t p = 1000; p <= 65535; p += 7) {
    const uint8_t k = oversample_log2(static_cast<uint16_t>(p));
    CHECK(((1u << k) + 1u) * STIPI_ADC_CONV_BUDGET_US + STIPI_ADC_MARGIN_US <= p);
  }
}

TEST(supply_reading_is_chained_only_when_it_lands_before_the_next_instant) {
  const uint16_t p = 2058;  // 486 Hz
  const uint16_t last = p - STIPI_ADC_CONV_BUDGET_US - STIPI_ADC_SUPPLY_SLACK_US;
  CHECK(supply_fits(0, p, false));
  CHECK(supply_fits(last, p, false));
  CHECK(!supply_fits(last + 1, p, false));
  CHECK(!supply_fits(p, p, false));
  CHECK(!supply_fits(0xFFFF, 0xFFFF, false));  // no wrap in the sum
  // The next instant has come (its flag pending; Timer1 has started again from 0): never.
  CHECK(!supply_fits(0, p, true));
  CHECK(!supply_fits(5, 62500, true));
  // At every rate oversample_log2 allows, an on-time sample (its conversions plus the latency
  // the margin is for) leaves room for the reading.
  for (uint32_t q = 1000; q <= 65535; q += 7) {
    const uint8_t k = oversample_log2(static_cast<uint16_t>(q));
    const uint32_t done = (1u << k) * STIPI_ADC_CONV_BUDGET_US + STIPI_ADC_MARGIN_US -
                          STIPI_ADC_SUPPLY_SLACK_US;
    CHECK(supply_fits(static_cast<uint16_t>(done), static_cast<uint16_t>(q), false));
  }
}

TEST(oversample_output_is_the_rounded_mean_on_the_wire_scale) {
  // 16 equal conversions of 700 give 700 (10-bit wire) whatever N is.
  for (uint8_t k = 0; k <= 4; ++k) {
    const uint32_t n = 1u << k;
    CHECK_EQ(oversample_output(700 * n, k, kGainOne), 700u << STIPI_ADC_EXTRA_BITS);
  }
  // The mean of 8 x 700 and 8 x 701 = 700.5: 10-bit rounds up, 12-bit keeps 2802.
  const uint32_t sum = 8 * 700 + 8 * 701;
  CHECK_EQ(oversample_output(sum, 4, kGainOne), STIPI_ADC_EXTRA_BITS == 2 ? 2802u : 701u);
  CHECK_EQ(oversample_output(16 * 1023, 4, kGainOne), (1u << STIPI_ADC_OUT_BITS) - 1);
  CHECK_EQ(oversample_output(0, 4, kGainOne), 0u);
  // A gain above 1 clips at full scale instead of wrapping.
  CHECK_EQ(oversample_output(16 * 1023, 4, 2 * kGainOne), (1u << STIPI_ADC_OUT_BITS) - 1);
}

TEST(supply_gain_is_nominal_over_measured_and_refuses_nonsense) {
  uint16_t gain = 0;
  // 776 counts = 2500.6 mV at the pin = 5001 mV: gain ~1.
  CHECK(supply_gain_q14(776, &gain));
  CHECK(gain >= kGainOne - 8 && gain <= kGainOne + 8);
  // A 4.75 V rail (737 counts): samples scaled up by ~5000/4750.
  CHECK(supply_gain_q14(737, &gain));
  const double g = gain / 16384.0;
  CHECK(g > 1.050 && g < 1.056);
  // 700 counts read at 4.75 V become ~737 (what 5 V would have given).
  CHECK_EQ(oversample_output(16 * 700, 4, gain), STIPI_ADC_EXTRA_BITS == 2 ? 2948u : 737u);
  // Nothing wired / a broken divider: no correction, refused.
  CHECK(!supply_gain_q14(0, &gain));
  CHECK_EQ(gain, kGainOne);
  CHECK(!supply_gain_q14(1023, &gain));
  CHECK_EQ(gain, kGainOne);
}

TEST(oversample_timestamp_is_the_middle_of_the_conversions) {
  CHECK_EQ(oversample_center_us(0), 0);
  CHECK_EQ(oversample_center_us(2), (3 * STIPI_ADC_CONV_PERIOD_US + 1) / 2);
  CHECK_EQ(oversample_center_us(4), (15 * STIPI_ADC_CONV_PERIOD_US + 1) / 2);
}

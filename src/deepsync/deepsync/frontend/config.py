"""Parameters of the envelope-detector receiver, from antenna to ADC codes."""

from __future__ import annotations

from dataclasses import dataclass

from deepsync.schema import check_settings, setting


@dataclass(frozen=True)
class FrontendConfig:
    """The receiver chain: LNA (+ RF noise) -> square-law diode -> video filter/amp -> ADC.

    Defaults describe a low-power LNA (30 dB, NF 6 dB: without gain ahead of it, a diode's
    own noise buries cells received at -60 dBm), a zero-bias Schottky detector (responsivity ~3 kV/W, noise-equivalent
    power ~5 pW/sqrt(Hz) into a high-impedance video amplifier), a 4th-order 0.9 MHz
    Butterworth anti-alias/video filter, AC coupling, and a 12-bit 1.92 MS/s ADC with a
    crystal clock. ``noise_temperature_k: 0`` and ``detector_nep_w_per_sqrt_hz: 0`` switch
    the RF and detector noise off (for checks of the noiseless chain). ``video_gain_db: null`` means the gain is set once, from the first 10 ms,
    so the signal sits at ``agc_target_dbfs`` (power-up AGC; held fixed afterwards). Every
    number must lie in its physical range (its :func:`~deepsync.schema.setting`): a value outside
    is a typo or a unit slip (MHz written in Hz, dB in linear), never a design; left through, it
    runs the simulator out of memory or overflows 10^(dB/10) far from the line that caused it.
    """

    # Below 0.1 MS/s a 71 us sync symbol spans < 8 samples; 61.44 MS/s (2 x 30.72) samples the
    # square of a 20 MHz carrier (|x|^2 spans +-18 MHz). Templates further need a rate that
    # divides 30.72 MHz (templates.check_template_rate); the simulator does not.
    adc_rate_hz: float = setting(1.92e6, help="ADC sample rate.", unit="Hz", bounds=(0.1e6, 61.44e6))
    # codes are int16; a 1-bit ADC keeps no envelope shape
    adc_bits: int = setting(12, help="ADC resolution.", unit="bits", bounds=(2, 16))
    # differential inputs of fast ADCs (~0.1 V) to +-10 V industrial ones
    adc_full_scale_v: float = setting(2.0, help="ADC full-scale input.", unit="V", bounds=(0.1, 20.0))
    # real converters are 0.3..3 LSB RMS; 16 LSB already wastes 4 bits
    adc_noise_lsb: float = setting(0.3, help="ADC noise.", unit="LSB RMS", bounds=(0.0, 16.0))
    # a crystal is within +-100 ppm; +-1000 ppm also covers a ceramic resonator
    clock_offset_ppm: float = setting(0.0, help="Receiver clock's frequency error.", unit="ppm",
                                      bounds=(-1000.0, 1000.0))
    # a crystal warming up drifts < 1 ppm/s
    clock_drift_ppm_per_s: float = setting(0.0, help="Receiver clock's drift.", unit="ppm/s", bounds=(-10.0, 10.0))
    # below 10 kHz the filter smears a 71 us sync symbol over several; 30.72 MHz passes the
    # envelope of any LTE carrier (and must stay below adc_rate_hz, checked below)
    video_cutoff_hz: float = setting(0.9e6, help="Video (anti-alias) filter's cutoff.", unit="Hz",
                                     bounds=(10e3, 30.72e6))
    # a Butterworth above 8th order rings for many symbols and is not built for a video path
    video_filter_order: int = setting(4, help="Video filter's Butterworth order; 0: no filter (a squared I/Q "
                                      "recording).", bounds=(0, 8))
    # AC coupling removes the diode's DC and slow drift only; above 1 kHz (time constant
    # 160 us) it starts to differentiate the 71 us sync symbols
    video_highpass_hz: float = setting(50.0, help="AC coupling's corner.", unit="Hz", bounds=(0.0, 1e3))
    # from a 40 dB pad (a strong signal into a sensitive ADC) to 100 dB, where the amplifier's
    # own input noise (~1 uV RMS in 1 MHz) already fills a tenth of a volt of the ADC
    video_gain_db: float | None = setting(None, help="Video amplifier's gain; null: set once from the first 10 ms "
                                          "so the signal sits at agc_target_dbfs.", unit="dB", bounds=(-40.0, 100.0))
    # the OFDM envelope peaks ~10 dB over its RMS: at -1 dBFS most peaks clip; at -60 dBFS a
    # 12-bit ADC sees the signal in ~2 codes
    agc_target_dbfs: float = setting(-20.0, help="Signal level the power-up AGC aims for.", unit="dBFS",
                                     bounds=(-60.0, -1.0))
    # a Schottky detector into a 50-ohm load (~10 V/W) to a zero-bias one into a
    # high-impedance video amplifier (a few kV/W, the best ~50 kV/W)
    detector_responsivity_v_per_w: float = setting(3000.0, help="Detector's responsivity.", unit="V/W",
                                                   bounds=(10.0, 1e5))
    # real diodes are ~1..50 pW/sqrt(Hz), and 1 nW/sqrt(Hz) would bury everything below ~-30 dBm
    # in a 1 MHz video bandwidth
    detector_nep_w_per_sqrt_hz: float = setting(5e-12, help="Detector's noise-equivalent power; 0: no detector "
                                                "noise.", unit="W/sqrt(Hz)", bounds=(0.0, 1e-9))
    # LNAs are 0.5..10 dB and a lossy input adds its loss; up to 100 dB so a test can raise
    # the thermal noise until it is measurable against a signal (the noise-density test
    # uses 80 dB), still far from overflowing 10^(NF/10)
    noise_figure_db: float = setting(6.0, help="RF chain's noise figure.", unit="dB", bounds=(0.0, 100.0))
    # a bare diode (0 dB) to two LNA stages; more would drive the diode out of its square law
    rf_gain_db: float = setting(30.0, help="RF gain ahead of the diode.", unit="dB", bounds=(0.0, 60.0))
    # an I/Q radio's passband at its sample rate (as narrow as adc_rate_hz) up to an unfiltered
    # wideband input (6 GHz)
    rf_bandwidth_hz: float = setting(200e6, help="RF bandwidth the noise is counted over.", unit="Hz",
                                     bounds=(0.1e6, 6e9))
    # electronics run at 233..358 K (-40..85 C), an antenna seeing hot surroundings somewhat more
    noise_temperature_k: float = setting(290.0, help="RF chain's noise temperature; 0: no RF noise.", unit="K",
                                         bounds=(0.0, 1000.0))

    def __post_init__(self) -> None:
        check_settings(self)
        if self.video_cutoff_hz >= self.adc_rate_hz:
            raise ValueError(
                f"video_cutoff_hz ({self.video_cutoff_hz:g}) must be below adc_rate_hz "
                f"({self.adc_rate_hz:g}); the video filter is the ADC's anti-alias filter"
            )
        if self.video_highpass_hz >= self.video_cutoff_hz / 10:
            raise ValueError(
                f"video_highpass_hz ({self.video_highpass_hz:g}) must be far below "
                f"video_cutoff_hz ({self.video_cutoff_hz:g})"
            )

    @property
    def rf_power_gain(self) -> float:
        """Linear power gain from the antenna to the diode."""
        return 10 ** (self.rf_gain_db / 10)

    @property
    def volts_per_code(self) -> float:
        return self.adc_full_scale_v / 2**self.adc_bits

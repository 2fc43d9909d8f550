pub struct DefurBaselineStage;

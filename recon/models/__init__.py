"""Scene representations behind one interface (`recon.models.base.Model`)."""

"""zenrl.replay"""
